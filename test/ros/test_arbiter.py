"""The tick's arbiter without ROS: the simulator's rules equal the evaluator's (PIBTShield,
resolve_moves), held robots and reserved cells, and the real-robot commands stay safe under
random delays (a plain-Python model of robots that arrive late or not at all)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mapf_fleet.coordination.pibt import PIBTShield
from mapf_fleet.coordination.rules import COORDINATED_RULES, PIBT_RULES, Rule
from mapf_fleet.grid.actions import ACTION_DELTAS
from mapf_fleet.grid.actions import actions_between
from mapf_fleet.grid.env import resolve_moves
from mapf_fleet.grid.instance import generate_instance
from mapf_fleet.fleet.arbiter import (CONFLICT_RULES, TickArbiter, break_rotations,
                                    check_conflict_rule,
                                    plan_robot_commands, ranking_problem, ready_to_send,
                                    single_choice_ranking, unsafe_commands)
from mapf_fleet.fleet.lockstep import FleetTicker


def _random_preferences(rng, n):
    return np.stack([rng.permutation(5) for _ in range(n)])


def test_rule_names_and_rankings():
    assert check_conflict_rule("pibt") == "pibt" and check_conflict_rule("revert") == "revert"
    assert check_conflict_rule("pibt_anchor") == "pibt_anchor"
    # every PIBT variant is a conflict rule of the simulator and the aggregator
    assert set(COORDINATED_RULES) < set(CONFLICT_RULES)
    assert check_conflict_rule("pibt_anchor_swap_hindrance") == "pibt_anchor_swap_hindrance"
    with pytest.raises(ValueError, match="conflict_rule"):
        check_conflict_rule("pibt_hindrance_swap")  # options in their order only
    with pytest.raises(ValueError, match="conflict_rule"):
        check_conflict_rule("swap")
    assert single_choice_ranking(3) == [3, 0, 1, 2, 4]
    assert single_choice_ranking(0) == [0, 1, 2, 3, 4]
    assert ranking_problem(2, [2, 0, 1, 3, 4]) == "" and ranking_problem(2, []) == ""
    assert "not a ranking" in ranking_problem(2, [2, 2, 1, 3, 4])
    assert "first of its ranking" in ranking_problem(1, [2, 0, 1, 3, 4])


@pytest.mark.parametrize("rule", PIBT_RULES)
def test_pibt_rule_is_the_evaluators_shield_tick_after_tick(rule):
    """Same positions, rankings and priorities as one PIBTShield per episode (the runner's
    `--conflict-rule pibt` / `pibt_anchor`)."""
    rng = np.random.default_rng(0)
    instance = generate_instance(10, 16, 0.25, 3)
    arbiter = TickArbiter(instance.grid, instance.goals, rule)
    shield = PIBTShield(instance.grid, instance.goals, **Rule.parse(rule).pibt_options())
    positions = np.asarray(instance.starts)
    overridden = 0
    for _ in range(30):
        prefs = _random_preferences(rng, len(positions))
        result = arbiter.resolve(positions, prefs)
        expected = shield.step(positions, prefs)
        np.testing.assert_array_equal(result.positions, expected.positions)
        np.testing.assert_array_equal(result.actions, expected.actions)
        np.testing.assert_array_equal(result.overridden, expected.overridden)
        assert not result.collided.any()
        overridden += result.overridden.sum()
        positions = result.positions
    assert overridden > 0 and arbiter.overridden_total == overridden


def test_revert_rule_is_resolve_moves_on_first_choices():
    rng = np.random.default_rng(1)
    instance = generate_instance(8, 14, 0.2, 5)
    arbiter = TickArbiter(instance.grid, instance.goals, "revert")
    positions = np.asarray(instance.starts)
    collided_any = False
    for _ in range(20):
        prefs = _random_preferences(rng, len(positions))
        result = arbiter.resolve(positions, prefs)
        nxt, collided = resolve_moves(instance.grid, positions, prefs[:, 0])
        np.testing.assert_array_equal(result.positions, nxt)
        np.testing.assert_array_equal(result.collided, collided)
        np.testing.assert_array_equal(result.actions, actions_between(positions, nxt))
        # a reverted move is an overridden first choice
        np.testing.assert_array_equal(result.overridden, result.actions != prefs[:, 0])
        collided_any |= collided.any()
        positions = result.positions
    assert collided_any


@pytest.mark.parametrize("rule", CONFLICT_RULES)
def test_held_robots_stay_reserved_cells_stay_free_and_commands_are_safe(rule):
    rng = np.random.default_rng(2 if rule != "revert" else 3)
    for seed in range(25):
        instance = generate_instance(8, 20, 0.25, seed)
        grid, positions = np.asarray(instance.grid), np.asarray(instance.starts)
        arbiter = TickArbiter(grid, instance.goals, rule)
        n = len(positions)
        held = rng.random(n) < 0.3
        # a held robot's reserved cell: a free neighbour of its cell (it is driving there)
        reserved = []
        for i in np.flatnonzero(held):
            for a in rng.permutation(4) + 1:
                cell = positions[i] + ACTION_DELTAS[a]
                if (0 <= cell).all() and (cell < grid.shape).all() and not grid[tuple(cell)]:
                    reserved.append(tuple(cell))
                    break
        result = arbiter.resolve(positions, _random_preferences(rng, n), held, reserved)
        assert not result.problem
        np.testing.assert_array_equal(result.positions[held], positions[held])
        assert unsafe_commands(grid, positions, result.positions, result.held, reserved) == []
        for i in range(n):
            if tuple(result.positions[i]) in set(reserved):
                assert (result.positions[i] == positions[i]).all()  # it stood there already


def test_overlapping_positions_make_everyone_stay():
    grid = np.zeros((3, 3), dtype=np.uint8)
    arbiter = TickArbiter(grid, [[0, 0], [2, 2]], "pibt")
    result = arbiter.resolve([[1, 1], [1, 1]], [[2, 0, 1, 3, 4], [1, 0, 2, 3, 4]])
    assert "share cells" in result.problem
    np.testing.assert_array_equal(result.positions, [[1, 1], [1, 1]])
    assert (result.actions == 0).all()


def test_unsafe_commands_names_each_breach():
    grid = np.zeros((3, 3), dtype=np.uint8)
    grid[2, 2] = 1
    pos = np.array([[0, 0], [0, 1], [1, 1], [2, 1]])
    assert unsafe_commands(grid, pos, pos) == []
    assert unsafe_commands(grid, pos, [[0, 1], [0, 0], [1, 1], [2, 1]])[0].endswith("trade cells")
    assert "one cell" in unsafe_commands(grid, pos, [[1, 0], [0, 1], [1, 0], [2, 1]])[0]
    assert "2 cells away" in unsafe_commands(grid, pos, [[1, 1], [0, 1], [1, 2], [2, 1]])[0]
    assert "obstacle" in unsafe_commands(grid, pos, [[0, 0], [0, 1], [1, 1], [2, 2]])[0]
    assert "off the map" in unsafe_commands(grid, pos, [[-1, 0], [0, 1], [1, 1], [2, 1]])[0]
    held = np.array([False, False, True, False])
    assert "held robot 2" in unsafe_commands(grid, pos, [[0, 0], [0, 1], [1, 2], [2, 1]], held)[0]
    assert "occupied" in unsafe_commands(grid, pos, [[1, 0], [0, 1], [1, 1], [2, 1]],
                                         reserved=[(1, 0)])[0]


def test_break_rotations_keeps_chains_and_stops_cycles():
    # four robots round a 2x2 block, a fifth following the first from the left
    pos = np.array([[0, 1], [0, 2], [1, 2], [1, 1], [0, 0]])
    commanded = np.array([[0, 2], [1, 2], [1, 1], [0, 1], [0, 1]])
    # (robot 4 into robot 0's cell would be a second follower of cell (0, 1): not a PIBT
    # output; give it its own cell instead)
    commanded[4] = [1, 0]
    out, stopped = break_rotations(pos, commanded)
    assert stopped == [0, 1, 2, 3]
    np.testing.assert_array_equal(out[:4], pos[:4])
    np.testing.assert_array_equal(out[4], [1, 0])
    chain = np.array([[0, 1], [0, 2], [1, 2]])  # 2 -> 1's cell -> ..., 0 into 1's cell
    out, stopped = break_rotations([[0, 0], [0, 1], [0, 2]], chain)
    assert stopped == [] and (out == chain).all()


def test_ready_to_send_waits_for_the_cell_to_be_vacated():
    commanded = np.array([[0, 1], [0, 2], [1, 1]])
    reported = {0: (0, 0), 1: (0, 1), 2: (1, 1)}
    assert ready_to_send(commanded, reported, [0, 1, 2]) == [1, 2]
    reported[1] = (0, 2)
    assert ready_to_send(commanded, reported, [0]) == [0]
    # robot 1's pose is rejected (off the map): it may still be in its last valid cell
    reported[1] = (-5, 1)
    assert ready_to_send(commanded, reported, [0], unsure={1: (0, 1)}) == []


def test_ticker_carries_rankings_and_falls_back_to_the_choice():
    ticker = FleetTicker(3, episode=4)

    def move(robot, action, prefs):
        return SimpleNamespace(episode=4, tick=0, robot_id=robot, action=action,
                               preferences=prefs, requested=[], messages_received=0,
                               missing_peers=[])

    assert ticker.on_move(move(0, 2, [2, 4, 0, 1, 3])) is None
    assert ticker.on_move(move(1, 3, [])) is None                  # no ranking: its choice
    assert "not a ranking" in ticker.on_move(move(2, 1, [1, 1, 0, 2, 3]))
    decisions = ticker.collect(0.01)
    np.testing.assert_array_equal(decisions.rankings,
                                  [[2, 4, 0, 1, 3], [3, 0, 1, 2, 4], [0, 1, 2, 3, 4]])
    np.testing.assert_array_equal(decisions.actions, [2, 3, 0])
    assert decisions.missing == [2]


@pytest.mark.parametrize("rule", ["pibt", "revert", "pibt_anchor_swap_hindrance", "pibt_swap"])
def test_real_robots_with_random_delays_never_share_a_cell(rule):
    """A plain-Python model of the aggregator's tick with robots that are slow: every robot
    sent a waypoint gets there at a random moment of the tick or only in a later tick. The
    commands, the followers' dispatch order and the arrivals must never put two robots in one
    cell, on an obstacle, or move one by more than one cell at a time."""
    rng = np.random.default_rng(7 if rule != "revert" else 8)
    instance = generate_instance(12, 30, 0.3, 11)
    grid = np.asarray(instance.grid)
    arbiter = TickArbiter(grid, instance.goals, rule)
    n = instance.num_agents
    actual = np.asarray(instance.starts).copy()      # where each robot physically is
    state = actual.copy()                            # the tick's state (snapped poses)
    waypoints = actual.copy()
    heading = {}                                     # robot -> waypoint it drives to
    late_seen = stopped_seen = moved = 0
    for _ in range(60):
        missing = [i for i in range(n) if rng.random() < 0.05]
        plan = plan_robot_commands(arbiter, state, waypoints, _random_preferences(rng, n), missing)
        assert plan.problems == []
        late_seen += int(plan.late.sum())
        stopped_seen += len(plan.stopped)
        commanded = plan.waypoints.copy()
        sent = np.zeros(n, dtype=bool)
        # the tick: events in random order until nothing changes or a random deadline
        for _ in range(int(rng.integers(1, 4 * n))):
            reported = {i: tuple(actual[i]) for i in range(n)}
            for i in ready_to_send(commanded, reported, np.flatnonzero(~sent).tolist()):
                sent[i] = True
                heading[i] = tuple(commanded[i])
            movers = [i for i, cell in heading.items() if tuple(actual[i]) != cell]
            if not movers:
                break
            i = movers[int(rng.integers(len(movers)))]
            if rng.random() < 0.7:  # it arrives now (else later)
                assert np.abs(np.asarray(heading[i]) - actual[i]).sum() == 1
                actual[i] = heading[i]
                moved += 1
                cells = {tuple(c) for c in actual}
                assert len(cells) == n, "two robots in one cell"
                assert not grid[tuple(actual[i])]
        unsent = ~sent & ~plan.late
        commanded[unsent] = state[unsent]
        waypoints = commanded
        state = actual.copy()
    assert moved > 50 and late_seen > 0


def test_fleet_up_defaults_to_the_fleet_rule_the_windowed_plan_over_anchor_and_swap():
    from mapf_fleet.fleet import parameters
    from mapf_fleet.ros.launcher import build_parser

    assert build_parser().parse_args([]).conflict_rule is None  # not given: the table's
    assert build_parser().parse_args(["--conflict-rule", "pibt"]).conflict_rule == "pibt"
    assert build_parser().parse_args(["--conflict-rule", "revert"]).conflict_rule == "revert"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--conflict-rule", "swap"])
    for table in (parameters.SIMULATOR, parameters.AGGREGATOR, parameters.POLICY):
        assert table["conflict_rule"].default == "pibt_anchor_swap_lns"
    for rule in CONFLICT_RULES:  # every rule reaches the simulator / aggregator
        assert build_parser().parse_args(["--conflict-rule", rule]).conflict_rule == rule
