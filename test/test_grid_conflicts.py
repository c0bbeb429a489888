"""Conflict rules of resolve_moves on hand-built cases, and against a literal port of the DHC
reference step as an oracle."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapf_fleet.grid.actions import ACTION_DELTAS, DOWN, LEFT, RIGHT, STAY, UP
from mapf_fleet.grid.env import resolve_moves


def run(positions, actions, grid=None, size=5):
    grid = np.zeros((size, size), np.uint8) if grid is None else np.asarray(grid, np.uint8)
    new, collided = resolve_moves(grid, np.array(positions), np.array(actions))
    return [tuple(p) for p in new.tolist()], collided.tolist()


def test_free_moves_and_stay():
    new, col = run([(2, 2), (0, 0)], [UP, STAY])
    assert new == [(1, 2), (0, 0)] and col == [False, False]


@pytest.mark.parametrize("pos,action", [((0, 2), UP), ((4, 2), DOWN), ((2, 0), LEFT),
                                        ((2, 4), RIGHT)])
def test_edge_of_map_reverts(pos, action):
    new, col = run([pos], [action])
    assert new == [pos] and col == [True]


def test_obstacle_reverts():
    grid = np.zeros((5, 5)); grid[2, 3] = 1
    new, col = run([(2, 2)], [RIGHT], grid)
    assert new == [(2, 2)] and col == [True]


def test_swap_reverts_both():
    new, col = run([(2, 1), (2, 2)], [RIGHT, LEFT])
    assert new == [(2, 1), (2, 2)] and col == [True, True]


@pytest.mark.parametrize("order", [(0, 1, 2), (2, 1, 0), (1, 2, 0)])
def test_vertex_conflict_lowest_index_wins(order):
    # three movers into (2, 2); agent indices permuted, the lowest index must win
    movers = [((2, 1), RIGHT), ((2, 3), LEFT), ((1, 2), DOWN)]
    positions = [None] * 3
    actions = [None] * 3
    for idx, (p, a) in zip(order, movers):
        positions[idx], actions[idx] = p, a
    new, col = run(positions, actions)
    assert new[0] == (2, 2) and col[0] is False
    assert new[1:] == positions[1:] and col[1:] == [True, True]


def test_mover_into_staying_agent_reverts_even_with_lower_index():
    new, col = run([(2, 1), (2, 2)], [RIGHT, STAY])
    assert new == [(2, 1), (2, 2)] and col == [True, False]


def test_stayer_holds_cell_against_several_movers():
    new, col = run([(2, 1), (2, 3), (2, 2)], [RIGHT, LEFT, STAY])
    assert new == [(2, 1), (2, 3), (2, 2)] and col == [True, True, False]


def test_following_is_allowed():
    new, col = run([(2, 1), (2, 2), (2, 3)], [RIGHT, RIGHT, RIGHT])
    assert new == [(2, 2), (2, 3), (2, 4)] and col == [False] * 3


def test_rotation_cycle_is_allowed():
    # 2x2 block rotating clockwise: (0,0)->(0,1)->(1,1)->(1,0)->(0,0)
    new, col = run([(0, 0), (0, 1), (1, 1), (1, 0)], [RIGHT, DOWN, LEFT, UP])
    assert new == [(0, 1), (1, 1), (1, 0), (0, 0)] and col == [False] * 4


def test_longer_rotation_cycle_is_allowed():
    # 6-cycle around a 2x3 block
    pos = [(0, 0), (0, 1), (0, 2), (1, 2), (1, 1), (1, 0)]
    act = [RIGHT, RIGHT, DOWN, LEFT, LEFT, UP]
    new, col = run(pos, act)
    assert new == [(0, 1), (0, 2), (1, 2), (1, 1), (1, 0), (0, 0)] and col == [False] * 6


def test_cascade_behind_blocked_head():
    # a train moving right whose head hits the map edge: every follower reverts
    pos = [(2, 1), (2, 2), (2, 3), (2, 4)]
    new, col = run(pos, [RIGHT] * 4)
    assert new == pos and col == [True] * 4


def test_cascade_behind_vertex_loser():
    # agent 1 loses (2,2) to agent 0; agent 2 was following agent 1 and must revert too
    new, col = run([(1, 2), (3, 2), (4, 2)], [DOWN, UP, UP])
    assert new == [(2, 2), (3, 2), (4, 2)] and col == [False, True, True]


def test_cascade_reverts_earlier_vertex_winner():
    # 0 and 1 contest (2,2): 0 wins at first. But the occupant of (2,2), agent 2, cannot leave
    # (its target's occupant 3 is blocked by stayer 4), so 2 reverts and then 0 must revert too.
    pos = [(1, 2), (3, 2), (2, 2), (2, 3), (2, 4)]
    act = [DOWN, UP, RIGHT, RIGHT, STAY]
    new, col = run(pos, act)
    assert new == pos and col == [True, True, True, True, False]


def test_swap_blocks_follower():
    new, col = run([(2, 1), (2, 2), (2, 0)], [RIGHT, LEFT, RIGHT])
    assert new == [(2, 1), (2, 2), (2, 0)] and col == [True, True, True]


def test_bad_input_raises():
    grid = np.zeros((3, 3))
    with pytest.raises(ValueError, match="agent 1 action 7"):
        resolve_moves(grid, np.array([[0, 0], [1, 1]]), np.array([0, 7]))
    with pytest.raises(ValueError, match="agent 0 position"):
        resolve_moves(grid, np.array([[3, 0]]), np.array([0]))
    with pytest.raises(ValueError, match="share a cell"):
        resolve_moves(grid, np.array([[1, 1], [1, 1]]), np.array([0, 0]))


# --- oracle: literal port of the DHC reference environment's conflict checks -----------------

def reference_resolve(grid, positions, actions):
    n = len(positions)
    h, w = grid.shape
    pos = positions.copy()
    nxt = positions + ACTION_DELTAS[actions]
    collided = np.zeros(n, bool)
    checking = [i for i in range(n) if actions[i] != STAY]
    for i in checking.copy():
        r, c = nxt[i]
        if r < 0 or r >= h or c < 0 or c >= w or grid[r, c] == 1:
            nxt[i] = pos[i]; collided[i] = True; checking.remove(i)
    changed = True
    while changed:  # swaps
        changed = False
        for i in checking:
            target = np.flatnonzero(np.all(nxt[i] == pos, axis=1))
            if target.size:
                j = int(target[0])
                if np.array_equal(nxt[j], pos[i]):
                    nxt[i] = pos[i]; nxt[j] = pos[j]; collided[[i, j]] = True
                    checking.remove(i); checking.remove(j); changed = True
                    break
    changed = True
    while changed:  # vertex conflicts
        changed = False
        for i in checking:
            group = np.flatnonzero(np.all(nxt == nxt[i], axis=1)).tolist()
            if len(group) > 1:
                if all(g in checking for g in group):
                    group.remove(min(group))
                else:
                    group = [g for g in group if g in checking]
                for g in group:
                    nxt[g] = pos[g]; collided[g] = True; checking.remove(g)
                changed = True
                break
    return nxt, collided


@st.composite
def scenes(draw):
    h = draw(st.integers(1, 6)); w = draw(st.integers(1, 6))
    grid = np.array(draw(st.lists(st.booleans(), min_size=h * w, max_size=h * w)), np.uint8)
    grid = grid.reshape(h, w) * np.array(draw(st.lists(st.booleans(), min_size=h * w,
                                                        max_size=h * w))).reshape(h, w)
    free = np.flatnonzero(grid.ravel() == 0)
    if free.size == 0:
        grid[0, 0] = 0
        free = np.array([0])
    cells = draw(st.lists(st.sampled_from(free.tolist()), min_size=1, max_size=free.size,
                          unique=True))
    positions = np.stack(np.divmod(np.array(cells), w), axis=1)
    actions = np.array(draw(st.lists(st.integers(0, 4), min_size=len(cells),
                                     max_size=len(cells))))
    return grid, positions, actions


@settings(max_examples=400, deadline=None)
@given(scenes())
def test_matches_reference_and_invariants(scene):
    grid, positions, actions = scene
    new, collided = resolve_moves(grid, positions, actions)
    ref_new, ref_collided = reference_resolve(grid, positions, actions)
    assert np.array_equal(new, ref_new)
    assert np.array_equal(collided, ref_collided)
    # invariants: no shared cell, no swap, stays never collide, others end at target or start
    flat = [tuple(p) for p in new.tolist()]
    assert len(set(flat)) == len(flat)
    n = len(positions)
    for i in range(n):
        for j in range(n):
            if i != j:
                assert not (np.array_equal(new[i], positions[j]) and
                            np.array_equal(new[j], positions[i]))
    target = positions + ACTION_DELTAS[actions]
    assert not collided[actions == STAY].any()
    assert np.array_equal(new[collided], positions[collided])
    moved = ~collided & (actions != STAY)
    assert np.array_equal(new[moved], target[moved])
    assert not grid[new[:, 0], new[:, 1]].any()
