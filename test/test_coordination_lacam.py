"""The project's LaCAM: valid plans, complete where pymapf's LaCAM is, the root step follows the
given rankings, fixed agents and reserved cells at the root, determinism, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapf_fleet.coordination.lacam import LaCAM, check_plan
from mapf_fleet.coordination.planners import ClassicalPlanner, positions_to_actions
from mapf_fleet.grid.actions import STAY
from mapf_fleet.grid.instance import generate_instance


@st.composite
def small_instance(draw):
    size = draw(st.integers(3, 7))
    density = draw(st.sampled_from([0.0, 0.1, 0.25]))
    rng = np.random.default_rng(draw(st.integers(0, 100_000)))
    grid = rng.random((size, size)) < density
    free = np.argwhere(~grid)
    if len(free) < 2:
        grid[:] = False
        free = np.argwhere(~grid)
    n = draw(st.integers(1, max(1, len(free) // 2)))
    starts = free[rng.permutation(len(free))[:n]]
    goals = free[rng.permutation(len(free))[:n]]
    rankings = np.stack([rng.permutation(5) for _ in range(n)])
    return grid, starts, goals, rankings


@settings(max_examples=200, deadline=None)
@given(small_instance(), st.booleans(), st.booleans())
def test_every_plan_is_valid(instance, ranked, swap):
    """Any small map, any agents, with or without given rankings, successors with or without
    swap: a plan found is one move or wait per step, no vertex or swap conflict, no obstacle,
    from the starts to the goals."""
    grid, starts, goals, rankings = instance
    result = LaCAM(grid, seed=3, swap=swap).plan(
        starts, goals, rankings=rankings if ranked else None, time_limit=0.5, max_nodes=5000)
    if result.solved:
        assert check_plan(grid, result.positions, starts, goals) == []
        positions_to_actions(result.positions)  # one grid move per step
    else:
        assert result.reason


def test_check_plan_names_what_is_wrong():
    grid = np.zeros((1, 3), dtype=bool)
    swap = np.array([[[0, 0], [0, 1]], [[0, 1], [0, 0]]])
    assert any("trade cells" in p for p in check_plan(grid, swap))
    vertex = np.array([[[0, 0], [0, 2]], [[0, 1], [0, 1]]])
    assert any("share a cell" in p for p in check_plan(grid, vertex))
    jump = np.array([[[0, 0]], [[0, 2]]])
    assert any("jumps" in p for p in check_plan(grid, jump))
    assert check_plan(grid, np.array([[[0, 0], [0, 1]], [[0, 1], [0, 2]]])) == []  # following


def _reference_instances(count=30):
    rng = np.random.default_rng(7)
    out = []
    while len(out) < count:
        size, n = [(8, 6), (10, 12), (12, 20)][len(out) % 3]
        out.append(generate_instance(size, n, 0.2, rng))
    return out


@pytest.mark.slow
def test_complete_where_pymapf_lacam_is_and_plans_as_long():
    """30 small random instances: every one pymapf's LaCAM solves (5 s) we solve too, in
    plans of about the same length (the mean makespan within 25 %)."""
    reference = ClassicalPlanner("lacam", time_limit=5.0)
    ours_len, ref_len = [], []
    for inst in _reference_instances():
        ref = reference.plan(inst.grid, inst.starts, inst.goals)
        if not ref.complete:
            continue
        ours = LaCAM(inst.grid).plan(inst.starts, inst.goals, time_limit=5.0)
        assert ours.solved, ours.reason
        assert check_plan(inst.grid, ours.positions, inst.starts, inst.goals) == []
        ours_len.append(len(ours.positions) - 1)
        ref_len.append(len(ref.positions) - 1)
    assert len(ref_len) >= 25
    assert np.mean(ours_len) <= 1.25 * np.mean(ref_len)


def test_unsolvable_instance_exhausts_the_search():
    """Two agents trading ends of a one-cell-wide corridor: no plan exists, and the search
    says so instead of spending the budget."""
    grid = np.zeros((1, 4), dtype=bool)
    result = LaCAM(grid).plan([[0, 0], [0, 3]], [[0, 3], [0, 0]], time_limit=5.0)
    assert not result.solved
    assert "exhausted" in result.reason
    assert result.seconds < 1.0


def test_solvability_tells_proven_unsolvable_from_solved_and_undecided():
    """A pocket where two agents must pass each other (the generated maps' unsolvable case)
    beside a region that is solvable: the instance is proven unsolvable; with room to pass it is
    solved (with its makespan); a budget too small to decide says so."""
    from mapf_fleet.coordination.lacam import solvability

    grid = np.ones((4, 6), dtype=bool)
    grid[0, 0:3] = False  # a 3-cell corridor
    grid[2:4, 2:6] = False  # an open 2x4 room
    starts, goals = [[0, 0], [0, 1], [2, 2]], [[0, 1], [0, 0], [3, 5]]
    assert solvability(grid, starts, goals) == ("unsolvable", None)
    kind, makespan = solvability(grid, [[2, 2], [2, 3]], [[2, 3], [2, 2]])
    assert kind == "solved" and makespan >= 3  # the swap takes 3 steps at least
    big = generate_instance(20, 60, 0.1, np.random.default_rng(0))
    assert solvability(big.grid, big.starts, big.goals, max_nodes=1)[0] == "undecided"


def test_unreachable_goal_is_refused_at_once():
    grid = np.array([[0, 1, 0]], dtype=bool)
    result = LaCAM(grid).plan([[0, 0]], [[0, 2]])
    assert not result.solved and "cannot reach" in result.reason


def test_root_step_follows_the_given_rankings():
    """Agents far apart on an open map: the plan's first step is every agent's first-ranked
    move, whatever the ranking (moves away from the goal and waits included)."""
    grid = np.zeros((12, 12), dtype=bool)
    starts = np.array([[2, 2], [2, 9], [9, 2], [9, 9]])
    goals = np.array([[5, 5], [5, 6], [6, 5], [6, 6]])
    rng = np.random.default_rng(0)
    for _ in range(10):
        rankings = np.stack([rng.permutation(5) for _ in range(4)])
        result = LaCAM(grid).plan(starts, goals, rankings=rankings, time_limit=2.0)
        assert result.solved
        first = positions_to_actions(result.positions[:2])[0]
        assert first.tolist() == rankings[:, 0].tolist()


def test_root_step_takes_the_next_ranked_move_when_the_first_is_taken():
    """Agent 1 ranks a move into the cell agent 0 (higher priority) takes first: it gets its
    second-ranked move instead."""
    grid = np.zeros((5, 5), dtype=bool)
    starts = np.array([[2, 1], [2, 3]])
    goals = np.array([[2, 4], [0, 0]])
    right, left, up = 4, 3, 1
    rankings = np.array([[right, STAY, 1, 2, left], [left, up, STAY, 2, right]])
    result = LaCAM(grid).plan(starts, goals, rankings=rankings, priorities=[1.0, 0.5],
                              time_limit=2.0)
    assert result.solved
    first = positions_to_actions(result.positions[:2])[0]
    assert first.tolist() == [right, up]


def test_deeper_steps_follow_distances():
    """Agents alone on an open map, root rankings that ask for a move closer to the goal: the
    whole plan is a shortest path (every step after the root is ranked by distance)."""
    grid = np.zeros((8, 8), dtype=bool)
    right, down = 4, 2
    starts = np.array([[0, 0], [7, 0]])
    goals = np.array([[6, 7], [7, 7]])
    rankings = np.array([[right, down, STAY, 1, 3], [right, STAY, 1, 2, 3]])
    result = LaCAM(grid).plan(starts, goals, rankings=rankings)
    assert result.solved
    assert len(result.positions) - 1 == 13
    assert (result.positions[1] == [[0, 1], [7, 1]]).all()


def test_fixed_agents_stay_and_reserved_cells_stay_free_on_the_first_step():
    grid = np.zeros((4, 4), dtype=bool)
    starts = np.array([[0, 0], [3, 3], [0, 3]])
    goals = np.array([[3, 0], [0, 3], [3, 3]])
    result = LaCAM(grid).plan(starts, goals, fixed=[False, True, False], reserved=[(1, 0)],
                              time_limit=2.0)
    assert result.solved
    assert check_plan(grid, result.positions, starts, goals) == []
    assert (result.positions[1, 1] == starts[1]).all()
    assert not (result.positions[1] == [1, 0]).all(axis=1).any()


def test_swap_solves_the_dense_maps_plain_successors_do_not():
    """The ceiling's dense maps (21 cells, density 0.25, 64 agents; the instances of
    docs/results.md "The expert ceiling"): with the same node budget, swap's successors solve
    every one of the first 5, plain PIBT's fewer."""
    from mapf_fleet.training.dagger.ceiling import ceiling_instances

    instances = ceiling_instances({"kind": "dense", "size": 21, "max_steps": 128}, 64, 5, 0)
    solved = {False: 0, True: 0}
    for inst in instances:
        for swap in (False, True):
            result = LaCAM(inst.grid, swap=swap).plan(inst.starts, inst.goals, time_limit=60,
                                                      max_nodes=2000)
            if result.solved:
                assert check_plan(inst.grid, result.positions, inst.starts, inst.goals) == []
                solved[swap] += 1
    assert solved[True] == 5 and solved[False] < 5


def test_deterministic_for_a_seed():
    inst = generate_instance(12, 24, 0.2, np.random.default_rng(3))
    a = LaCAM(inst.grid, seed=5).plan(inst.starts, inst.goals)
    b = LaCAM(inst.grid, seed=5).plan(inst.starts, inst.goals)
    assert a.solved and np.array_equal(a.positions, b.positions) and a.nodes == b.nodes


def test_node_budget_is_kept():
    inst = generate_instance(12, 40, 0.2, np.random.default_rng(3))
    result = LaCAM(inst.grid).plan(inst.starts, inst.goals, max_nodes=3)
    assert not result.solved and "node budget" in result.reason and result.nodes <= 3


def test_bad_input_is_named():
    planner = LaCAM(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="starts: agent 0 at \\(5, 0\\)"):
        planner.plan([[5, 0]], [[0, 0]])
    with pytest.raises(ValueError, match="share a goal"):
        planner.plan([[0, 0], [1, 1]], [[2, 2], [2, 2]])
    with pytest.raises(ValueError, match="not a ranking"):
        planner.plan([[0, 0]], [[2, 2]], rankings=[[0, 0, 1, 2, 3]])

