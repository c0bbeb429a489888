"""The PIBT shield: safety properties for any rankings, PIBT's behaviour, determinism."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapf_fleet.coordination.pibt import PIBTShield
from mapf_fleet.coordination.ranking import validate_rankings
from mapf_fleet.coordination.ranking import distance_classes, rank_actions
from mapf_fleet.grid.actions import ACTION_DELTAS, DOWN, LEFT, RIGHT, STAY, UP
from mapf_fleet.grid.env import MAPFEnv, resolve_moves
from mapf_fleet.grid.instance import Instance, generate_instance


def assert_safe(grid, before, after, reserved=()):
    grid = np.asarray(grid) != 0
    h, w = grid.shape
    assert ((after >= 0) & (after < [h, w])).all(), "off the map"
    assert not grid[after[:, 0], after[:, 1]].any(), "onto an obstacle"
    assert len({tuple(p) for p in after.tolist()}) == len(after), "vertex conflict"
    assert (np.abs(after - before).sum(1) <= 1).all(), "a jump of more than one cell"
    now = {tuple(p): i for i, p in enumerate(before.tolist())}
    for i, p in enumerate(after.tolist()):
        j = now.get(tuple(p))
        if j is not None and j != i:
            assert tuple(after[j]) != tuple(before[i]), f"swap of agents {i} and {j}"
    for cell in reserved:
        entered = [i for i in range(len(after)) if tuple(after[i]) == tuple(cell)
                   and tuple(before[i]) != tuple(cell)]
        assert not entered, f"agents {entered} entered the reserved cell {cell}"


@st.composite
def crowded_tick(draw):
    size = draw(st.integers(3, 8))
    density = draw(st.sampled_from([0.0, 0.1, 0.3]))
    free_needed = 2
    seed = draw(st.integers(0, 10_000))
    rng = np.random.default_rng(seed)
    grid = rng.random((size, size)) < density
    free = np.argwhere(~grid)
    if len(free) < free_needed:
        grid[:] = False
        free = np.argwhere(~grid)
    n = draw(st.integers(1, len(free)))  # up to a completely full map
    cells = free[rng.permutation(len(free))[:n]]
    goals = free[rng.permutation(len(free))[:n]]
    prefs = np.stack([rng.permutation(5) for _ in range(n)])
    fixed = rng.random(n) < draw(st.sampled_from([0.0, 0.2]))
    return grid, cells, goals, prefs, fixed


@settings(max_examples=300, deadline=None)
@given(crowded_tick(), st.integers(1, 4), st.booleans())
def test_no_conflict_ever(tick, steps, anchor):
    """Random maps up to completely full, random rankings, some fixed agents, several steps,
    with and without the anchor: never a vertex conflict, a swap, an obstacle, the map's edge or
    a jump; fixed agents stay."""
    grid, positions, goals, prefs, fixed = tick
    shield = PIBTShield(grid, goals, anchor=anchor)
    rng = np.random.default_rng(len(positions))
    for _ in range(steps):
        result = shield.step(positions, prefs, fixed=fixed)
        assert_safe(grid, positions, result.positions)
        assert (result.positions[fixed] == positions[fixed]).all()
        moved = result.positions - positions
        assert (ACTION_DELTAS[result.actions] == moved).all()
        # the environment's revert rules accept every shielded move: nothing collides
        _, collided = resolve_moves(grid, positions, result.actions)
        assert not collided.any()
        positions = result.positions
        prefs = np.stack([rng.permutation(5) for _ in range(len(positions))])


@settings(max_examples=100, deadline=None)
@given(crowded_tick())
def test_reserved_cells_stay_free(tick):
    grid, positions, goals, prefs, _ = tick
    free = np.argwhere(~np.asarray(grid))
    occupied = {tuple(p) for p in positions.tolist()}
    empty = [tuple(c) for c in free.tolist() if tuple(c) not in occupied]
    reserved = empty[:3]
    result = PIBTShield(grid, goals).step(positions, prefs, reserved=reserved)
    assert_safe(grid, positions, result.positions, reserved)


def test_first_choices_are_kept_without_conflicts():
    grid = np.zeros((5, 5), dtype=bool)
    positions = np.array([[0, 0], [4, 4]])
    prefs = np.array([[RIGHT, STAY, UP, DOWN, LEFT], [UP, STAY, DOWN, LEFT, RIGHT]])
    result = PIBTShield(grid, positions).step(positions, prefs)
    assert result.positions.tolist() == [[0, 1], [3, 4]]
    assert result.actions.tolist() == [RIGHT, UP]
    assert not result.overridden.any()


def test_priority_inheritance_pushes_the_occupant_out_of_the_way():
    """A corridor: agent 1 (higher priority: higher tie-breaker) wants agent 0's cell; agent 0
    prefers to stay but is pushed along its own ranking."""
    grid = np.ones((3, 5), dtype=bool)
    grid[1, :] = False
    positions = np.array([[1, 2], [1, 1]])
    prefs = np.array([[STAY, RIGHT, LEFT, UP, DOWN],   # 0 would rather stay
                      [RIGHT, STAY, LEFT, UP, DOWN]])  # 1 wants 0's cell
    result = PIBTShield(grid, [[1, 2], [1, 4]]).step(positions, prefs)
    assert result.positions.tolist() == [[1, 3], [1, 2]]
    assert result.overridden.tolist() == [True, False]


def test_fixed_agents_are_never_pushed():
    grid = np.ones((3, 5), dtype=bool)
    grid[1, :] = False
    positions = np.array([[1, 2], [1, 1]])
    prefs = np.array([[STAY, RIGHT, LEFT, UP, DOWN], [RIGHT, STAY, LEFT, UP, DOWN]])
    result = PIBTShield(grid, [[1, 2], [1, 4]]).step(positions, prefs, fixed=[True, False])
    assert result.positions.tolist() == [[1, 2], [1, 1]]
    assert result.overridden.tolist() == [False, True]


def test_backtracking_when_the_occupant_is_trapped():
    """Agent 1 wants agent 0's cell, but 0 sits in a dead end with nowhere to go: 1 backtracks
    to its second choice instead of failing."""
    grid = np.ones((3, 4), dtype=bool)
    grid[1, :] = False
    grid[0, 1] = False
    positions = np.array([[1, 0], [1, 1]])  # 0 in the dead end on the left
    prefs = np.array([[STAY, UP, DOWN, LEFT, RIGHT], [LEFT, UP, STAY, DOWN, RIGHT]])
    shield = PIBTShield(grid, [[1, 0], [0, 1]])
    shield.priorities = np.array([0.0, 5.0])
    result = shield.step(positions, prefs)
    assert result.positions.tolist() == [[1, 0], [0, 1]]


def test_priorities_rise_off_goal_and_reset_on_arrival():
    grid = np.zeros((1, 4), dtype=bool)
    shield = PIBTShield(grid, [[0, 1], [0, 3]])
    base = shield.priorities.copy()
    assert len(set(base.tolist())) == 2 and (base < 1).all()
    positions = np.array([[0, 0], [0, 2]])
    prefs = np.array([[RIGHT, STAY, LEFT, UP, DOWN], [STAY, RIGHT, LEFT, UP, DOWN]])
    shield.step(positions, prefs)  # 0 arrives, 1 stays off its goal
    assert shield.priorities[0] == base[0] and shield.priorities[1] == base[1] + 1
    shield.reset()
    assert (shield.priorities == base).all()


def test_deterministic_for_the_same_inputs():
    inst = generate_instance(20, 40, 0.3, 3)
    rng = np.random.default_rng(0)
    prefs = np.stack([rng.permutation(5) for _ in range(40)])
    a = PIBTShield(inst.grid, inst.goals).step(inst.starts, prefs)
    b = PIBTShield(inst.grid, inst.goals).step(inst.starts, prefs)
    assert (a.positions == b.positions).all() and (a.overridden == b.overridden).all()


def test_bad_input_is_named():
    shield = PIBTShield(np.zeros((3, 3)), [[0, 0], [2, 2]])
    with pytest.raises(ValueError, match="agent 1: ranking"):
        shield.step([[0, 0], [1, 1]], [[0, 1, 2, 3, 4], [0, 0, 1, 2, 3]])
    with pytest.raises(ValueError, match="outside the 3x3 map"):
        shield.step([[0, 0], [3, 1]], [[0, 1, 2, 3, 4]] * 2)
    with pytest.raises(ValueError, match=r"agents \[0, 1\] share"):
        shield.step([[1, 1], [1, 1]], [[0, 1, 2, 3, 4]] * 2)
    with pytest.raises(ValueError, match="shape"):
        validate_rankings(np.zeros((2, 4), dtype=int), 2)


# --- rankings ---------------------------------------------------------------------------------

def test_distance_order_follows_the_heuristic_bits():
    """On an open map the distance ranking is: closer moves, stay, away, blocked."""
    grid = np.zeros((5, 5), dtype=np.uint8)
    grid[2, 1] = 1  # obstacle left of the agent
    inst = Instance(grid, np.array([[2, 2]]), np.array([[0, 4]]))
    obs = MAPFEnv(inst).reset()
    classes = distance_classes(obs)[0]
    assert classes.tolist() == [1, 0, 2, 3, 0]  # stay, up closer, down away, left blocked, right closer
    assert rank_actions(obs, mode="distance")[0].tolist() == [UP, RIGHT, STAY, DOWN, LEFT]
    # distance_q: Q picks between the two closer moves and orders nothing across classes
    q = np.array([[9.0, 1.0, 5.0, 8.0, 2.0]])  # stay, up, down, left, right
    assert rank_actions(obs, q, "distance_q")[0].tolist() == [RIGHT, UP, STAY, DOWN, LEFT]


def test_q_rankings():
    grid = np.zeros((5, 5), dtype=np.uint8)
    inst = Instance(grid, np.array([[2, 2]]), np.array([[0, 2]]))  # goal straight up
    obs = MAPFEnv(inst).reset()
    q = np.array([[3.0, 2.0, 1.0, 2.5, 0.0]])  # stay, up, down, left, right
    assert rank_actions(obs, q, "q")[0].tolist() == [STAY, LEFT, UP, DOWN, RIGHT]
    # stay below the only closer move (up)
    assert rank_actions(obs, q, "q_demote_stay")[0].tolist() == [LEFT, UP, STAY, DOWN, RIGHT]
    # argmax first, then closer (up), then away moves by Q
    assert rank_actions(obs, q, "q_then_distance")[0].tolist() == [STAY, UP, LEFT, DOWN, RIGHT]
    # the distance order whatever Q says; Q orders only the away moves here
    assert rank_actions(obs, q, "distance_q")[0].tolist() == [UP, STAY, LEFT, DOWN, RIGHT]
    # on its goal nothing is closer: q_demote_stay keeps the Q order
    on_goal = MAPFEnv(Instance(grid, np.array([[2, 2]]), np.array([[2, 2]]))).reset()
    assert rank_actions(on_goal, q, "q_demote_stay")[0].tolist() == [STAY, LEFT, UP, DOWN, RIGHT]
    with pytest.raises(ValueError, match="needs Q-values"):
        rank_actions(obs, None, "q")
    with pytest.raises(ValueError, match="ranking must be one of"):
        rank_actions(obs, q, "bogus")


def _run(inst, choose):
    env = MAPFEnv(inst)
    obs = env.reset()
    for t in range(256):
        obs, _, done, info = env.step(choose(env, obs, t))
        assert not info["collisions"].any() or choose.__name__ == "unshielded"
        if done:
            return bool(info["success"])
    return False


def test_plain_pibt_solves_crowded_instances():
    """Distance rankings with per-tick tie-breakers under the shield (plain PIBT) solve
    crowded random instances that the heuristic under the revert rule does not, and the
    tie-breakers matter (a fixed action order livelocks)."""
    from mapf_fleet.coordination.ranking import tie_breakers
    from mapf_fleet.grid.policies import heuristic_policy

    instances = [generate_instance(16, 32, 0.2, seed) for seed in range(10)]

    def shielded(ties):
        def choose(env, obs, t):
            if not hasattr(choose, "shield") or choose.instance is not env.instance:
                choose.shield, choose.instance = PIBTShield(env.grid, env.goals), env.instance
            ids = np.arange(env.num_agents)
            prefs = rank_actions(obs, mode="distance", ties=tie_breakers(ids, t) if ties else None)
            return choose.shield.step(env.positions, prefs).actions
        return choose

    def unshielded(env, obs, t):
        return heuristic_policy(obs)

    with_ties = sum(_run(inst, shielded(True)) for inst in instances)
    fixed_order = sum(_run(inst, shielded(False)) for inst in instances)
    heuristic = sum(_run(inst, unshielded) for inst in instances)
    assert with_ties >= 7, with_ties
    assert with_ties > fixed_order
    assert heuristic <= 2


def test_anchor_puts_the_top_priority_agent_on_its_distance_order():
    """The highest-priority agent asks to stay (a learned ranking can); with the anchor it takes
    the move towards its goal, the others keep what they asked for, and the step counts as an
    override of its own choice."""
    grid = np.zeros((5, 5), dtype=bool)
    positions = np.array([[4, 0], [0, 0]])
    goals = np.array([[4, 4], [0, 4]])
    stay_first = np.array([[STAY, RIGHT, UP, DOWN, LEFT], [STAY, RIGHT, UP, DOWN, LEFT]])
    plain = PIBTShield(grid, goals).step(positions, stay_first)
    assert plain.positions.tolist() == positions.tolist()  # CS-PIBT keeps both first choices
    anchored = PIBTShield(grid, goals, anchor=True)
    result = anchored.step(positions, stay_first)
    # agent 1 has the higher tie-breaker, so the top priority at the first tick
    assert result.positions.tolist() == [[4, 0], [0, 1]]
    assert result.overridden.tolist() == [False, True]
    assert anchored.distance_map(1)[0 * 5 + 0] == 4 and anchored.distance_map(1)[4 * 5 + 0] == 8


def test_anchored_ranking_is_plain_pibts_distance_ranking():
    """The anchor ranks like the evaluator's plain PIBT (distance classes from the observation,
    the same per-tick hash), so the heuristic under either shield plays the same moves."""
    from mapf_fleet.evaluation.protocol import InstanceSet
    from mapf_fleet.evaluation.policies import HeuristicBatchPolicy
    from mapf_fleet.evaluation.runner import run_decentralized

    instances = InstanceSet.from_instances([generate_instance(12, 20, 0.2, s) for s in range(4)], "t")
    plain = run_decentralized(HeuristicBatchPolicy(), instances, 64, conflict_rule="pibt")
    anchor = run_decentralized(HeuristicBatchPolicy(), instances, 64, conflict_rule="pibt_anchor")
    assert [r.steps for r in plain] == [r.steps for r in anchor]
    assert [r.sum_of_costs for r in plain] == [r.sum_of_costs for r in anchor]


def test_anchored_ranking_puts_blocked_moves_last_on_every_numpy():
    """Issue 40 item 7: the anchored (plain PIBT) ranking keyed blocked moves by int64's max in
    an int32 array: numpy 2.4 wrapped it to -1 (blocked moves ranked first, so an anchored agent
    taking its best free move was counted as overridden) and numpy 2.5 raised OverflowError at
    the first tick. Blocked moves come last, and the agent's best free move is its first choice."""
    grid = np.array([[1, 1, 1, 1, 1, 0, 1],
                     [0, 0, 0, 0, 0, 0, 0]])
    shield = PIBTShield(grid, [(1, 6)], anchor=True)
    ranking = shield.anchored_ranking(0, 1 * 7 + 2).tolist()
    assert ranking[0] == 4  # right: closer to (1, 6)
    assert set(ranking[-2:]) == {1, 2}  # up (an obstacle) and down (off the map) last
    from mapf_fleet.coordination.plan import distance_rankings

    positions = np.array([(1, 2)])
    step = shield.step(positions, distance_rankings(shield, positions))
    assert step.actions.tolist() == [4] and not step.overridden[0]
