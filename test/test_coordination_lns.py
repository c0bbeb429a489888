"""The `_lns` rules (`coordination.lns`): the rule names, the space-time search, the safety
guarantees of the PIBT rules for every LNS rule (the tick is `PIBTShield.step`), the plan's own
conflict-freeness over the window, that a repair only ever lowers the plan's cost, what the
window buys (a corridor one-step PIBT enters from both ends), reproducibility, and the callers."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapf_fleet.coordination.factory import make_shield
from mapf_fleet.coordination.lns import LNSShield, window_search
from mapf_fleet.coordination.rules import (CONFLICT_RULES, EPIBT_RULES, LNS_WINDOW, LNS_RULES,
                                           PIBT_RULES, Rule)
from mapf_fleet.evaluation.protocol import DEFAULT_TESTSETS
from mapf_fleet.grid.actions import ACTION_DELTAS, move_targets
from mapf_fleet.grid.env import resolve_moves
from mapf_fleet.grid.instance import generate_instance

from test_coordination_epibt import CORRIDOR, _assert_plan_conflict_free, _solve
from test_coordination_pibt_variants import assert_safe, crowded_tick, distance_rankings

LNS_OPTIONS = [Rule.parse(rule).pibt_options() for rule in LNS_RULES]


# --- names ---------------------------------------------------------------------------------------
def test_lns_rule_names_parse_build_and_reach_the_callers():
    assert LNS_RULES == ("pibt_lns", "pibt_anchor_lns", "pibt_swap_lns", "pibt_anchor_swap_lns",
                         "pibt_patient_lns", "pibt_patient_swap_lns")
    assert set(LNS_RULES) <= set(CONFLICT_RULES)
    assert not set(LNS_RULES) & (set(PIBT_RULES) | set(EPIBT_RULES))
    grid = np.zeros((4, 4), dtype=np.uint8)
    goals = np.array([[0, 0], [3, 3]])
    for name in LNS_RULES:
        rule = Rule.parse(name)
        assert rule.is_pibt and rule.coordinated and rule.lns and not rule.epibt
        assert rule.window == LNS_WINDOW
        plain = Rule.parse(name.removesuffix("_lns"))
        assert rule.pibt_options() == plain.pibt_options() and not plain.lns
        assert Rule.pibt(**rule.pibt_options(), lns=True) == rule
        assert rule.default_ranking == plain.default_ranking
        shield = make_shield(name, grid, goals)
        assert isinstance(shield, LNSShield) and shield.window == LNS_WINDOW
    for bad in ("pibt_hindrance_lns", "pibt_lns_swap", "lns", "lacam_lns",
                "pibt_anchor_swap_epibt_lns"):
        with pytest.raises(ValueError, match=f"conflict rule must be one of .*got '{bad}'"):
            Rule.parse(bad)
    with pytest.raises(ValueError, match="hindrance"):
        LNSShield(grid, goals, hindrance=True)
    with pytest.raises(ValueError, match="window must be >= 1, got 0"):
        LNSShield(grid, goals, window=0)

    from mapf_fleet.evaluation.cli import build_parser as evaluate_parser
    from mapf_fleet.fleet.arbiter import check_conflict_rule

    assert evaluate_parser().parse_args(["--conflict-rule", *LNS_RULES]).conflict_rule == \
        list(LNS_RULES)
    assert check_conflict_rule("pibt_anchor_swap_lns") == "pibt_anchor_swap_lns"


def test_the_plan_reads_the_rules_constants_when_built(monkeypatch):
    """`rules.LNS_*` are the one place the plan's settings live: a shield built after they change
    takes the new values (they were once bound at import, so changing them did nothing)."""
    from mapf_fleet.coordination import rules

    grid = np.zeros((4, 4), dtype=np.uint8)
    goals = np.array([[0, 0], [3, 3]])
    monkeypatch.setattr(rules, "LNS_WINDOW", 5)
    monkeypatch.setattr(rules, "LNS_ITERATIONS", 7)
    monkeypatch.setattr(rules, "LNS_NEIGHBOURHOOD", 3)
    shield = make_shield("pibt_anchor_swap_lns", grid, goals)
    assert (shield.window, shield.iterations, shield.neighbourhood) == (5, 7, 3)
    assert LNSShield(grid, goals, window=2).window == 2  # an argument still wins


# --- the space-time search -----------------------------------------------------------------------
def _search(rows, start, goal, window, occ_paths=(), reserved=()):
    grid = np.array([[c == "#" for c in row] for row in rows])
    h, w = grid.shape
    targets = move_targets(grid)
    costs = np.ones(targets.shape)
    from mapf_fleet.grid.heuristic import distance_table

    dist = np.asarray(distance_table(grid).row(goal[0] * w + goal[1]), dtype=np.float64)
    occ = np.full((window + 1, h * w), -1, dtype=np.int32)
    for j, path in enumerate(occ_paths):
        occ[np.arange(window + 1), [r * w + c for r, c in path]] = j
    for r, c in reserved:
        occ[1:, r * w + c] = -2
    path, cost = window_search(start[0] * w + start[1], goal[0] * w + goal[1], dist, targets,
                               costs, occ, window)
    return [divmod(int(c), w) for c in path], cost


def test_window_search_is_the_shortest_way_and_waits_on_the_goal_for_free():
    rows = ["....", ".##.", "...."]
    path, cost = _search(rows, (0, 0), (2, 3), 8)
    assert path[0] == (0, 0) and path[5:] == [(2, 3)] * 4 and cost == 5.0
    path, cost = _search(rows, (0, 0), (2, 3), 3)  # the window ends on the way: 3 + distance 2
    assert len(path) == 4 and cost == 5.0
    for a, b in zip(path, path[1:]):
        assert abs(a[0] - b[0]) + abs(a[1] - b[1]) == 1


def test_window_search_meets_no_path_and_no_trade():
    rows = ["....."]
    # another agent walks from (0, 4) to (0, 1): ours from (0, 0) cannot pass it in one row
    other = [(0, 4), (0, 3), (0, 2), (0, 1), (0, 1), (0, 1)]
    path, cost = _search(rows, (0, 0), (0, 4), 5, [other])
    assert path[0] == (0, 0)
    for t in range(1, 6):
        assert path[t] != other[t]
        assert not (path[t] == other[t - 1] and other[t] == path[t - 1])
    assert cost > 4.0  # it cannot get there
    path, _ = _search(["..", ".."], (0, 0), (0, 1), 2, reserved=[(0, 1)])
    assert (0, 1) not in path[1:]
    # boxed in by a reserved cell and an agent that stays: no move, waiting is the way
    path, cost = _search(["..."], (0, 0), (0, 2), 2, [[(0, 2)] * 3], reserved=[(0, 1)])
    assert path == [(0, 0)] * 3 and cost == 2.0 + 2.0
    # every cell taken at step 1: no path
    path, cost = _search([".."], (0, 0), (0, 1), 2, [[(0, 1), (0, 0), (0, 0)]])
    assert path[0] == -1 or cost == np.inf


# --- safety --------------------------------------------------------------------------------------
@settings(max_examples=60, deadline=None)
@given(crowded_tick(), st.integers(0, len(LNS_RULES) - 1),
       st.sampled_from(["random", "distance", "mixed"]), st.booleans())
def test_no_conflict_for_any_lns_rule(tick, which, rankings, with_reserved):
    """As the PIBT rules' property test: random maps (up to full), random / distance / mixed
    rankings, fixed agents, reserved cells, several ticks (the plan kept between them): never two
    agents in one cell, never two trading cells, never an obstacle, the edge or a jump; fixed
    agents stay; reserved cells stay free; the environment finds nothing to revert."""
    grid, positions, goals, fixed, rng = tick
    shield = LNSShield(grid, goals, **LNS_OPTIONS[which], window=4, iterations=16)
    for _ in range(3):
        n = len(positions)
        prefs = np.stack([rng.permutation(5) for _ in range(n)])
        if rankings != "random":
            dist = distance_rankings(shield, positions)
            use = np.ones(n, bool) if rankings == "distance" else rng.random(n) < 0.5
            prefs[use] = dist[use]
        reserved = []
        if with_reserved:
            for i in np.flatnonzero(fixed):
                cell = positions[i] + ACTION_DELTAS[rng.integers(1, 5)]
                if (cell >= 0).all() and (cell < grid.shape).all() and not grid[tuple(cell)]:
                    reserved.append(tuple(int(x) for x in cell))
        held = fixed | np.array([tuple(p) in set(reserved) for p in positions.tolist()])
        plan = shield.plan(positions, prefs, fixed=fixed, reserved=reserved)
        _assert_plan_conflict_free(grid, positions, plan, held, reserved)
        result = shield.step(positions, prefs, fixed=fixed, reserved=reserved)
        assert_safe(grid, positions, result.positions, fixed, reserved)
        assert (ACTION_DELTAS[result.actions] == result.positions - positions).all()
        _, collided = resolve_moves(grid, positions, result.actions)
        assert not collided.any()
        assert (result.overridden == ((result.actions != prefs[:, 0]) & ~held)).all()
        positions = result.positions


def test_long_lifelong_runs_stay_safe_and_the_repair_only_lowers_the_cost():
    """Crowded generated maps, 30 ticks each with new goals on arrival, some random rankings and
    a few fixed agents, under highways guidance on half of them: safe at every tick, the plan
    conflict-free over its window, and its cost never above the rollout's (the repair keeps a
    neighbourhood's new paths only when they cost less)."""
    from mapf_fleet.grid.guidance_made import highways

    improved = 0
    for seed, which in zip(range(6), range(len(LNS_RULES))):
        inst = generate_instance(12, 40, 0.3, seed)
        grid = np.asarray(inst.grid)
        guidance = highways(grid) if seed % 2 else None
        shield = LNSShield(grid, inst.goals, **LNS_OPTIONS[which], guidance=guidance)
        rng = np.random.default_rng(seed)
        positions, goals = np.asarray(inst.starts), np.asarray(inst.goals).copy()
        free = np.argwhere(grid == 0)
        for _ in range(30):
            n = len(positions)
            prefs = distance_rankings(shield, positions)
            for i in np.flatnonzero(rng.random(n) < 0.25):
                prefs[i] = rng.permutation(5)
            fixed = rng.random(n) < 0.05
            state = shield.snapshot()
            rows = shield._agent_rows()
            rollout = shield._rollout(positions, prefs, fixed, (), rows)
            plan = shield.plan(positions, prefs, fixed=fixed)
            shield.restore(state)
            _assert_plan_conflict_free(grid, positions, plan, fixed)
            assert shield._costs(plan, rows).sum() <= shield._costs(rollout, rows).sum() + 1e-9
            result = shield.step(positions, prefs, fixed=fixed)
            improved += shield.improved
            assert_safe(grid, positions, result.positions, fixed)
            positions = result.positions
            arrived = (positions == goals).all(axis=1)
            goals[arrived] = free[rng.integers(len(free), size=int(arrived.sum()))]
            shield.set_goals(goals)
    assert improved > 0  # the repair did something on these crowded maps


# --- what the window buys ------------------------------------------------------------------------
@pytest.mark.parametrize("rule", ["pibt", "pibt_anchor_swap"])
def test_lns_crosses_a_corridor_that_one_step_pibt_enters_from_both_ends(rule):
    """Two agents trade ends of a three-cell corridor (EPIBT's test): one-step PIBT takes 19
    ticks; under the windowed plan one agent steps aside before the other enters: 9 ticks."""
    starts, goals = [(0, 2), (4, 2)], [(4, 2), (0, 2)]
    assert _solve(rule, CORRIDOR, starts, goals) == 19
    assert _solve(f"{rule}_lns", CORRIDOR, starts, goals) <= 9


def test_a_run_is_reproducible():
    """The repair draws from a generator seeded by the tick: two shields, the same ticks."""
    inst = generate_instance(12, 40, 0.3, 7)
    grid = np.asarray(inst.grid)
    runs = []
    for _ in range(2):
        shield = make_shield("pibt_anchor_swap_lns", grid, inst.goals)
        positions, trace = np.asarray(inst.starts), []
        for _ in range(15):
            positions = shield.step(positions, distance_rankings(shield, positions)).positions
            trace.append(positions.copy())
        runs.append(np.stack(trace))
    assert np.array_equal(runs[0], runs[1])


# --- the callers ---------------------------------------------------------------------------------
def test_lns_rule_runs_through_the_fleet_core_and_the_lifelong_evaluator():
    """A lifelong `FleetRun` under `pibt_anchor_swap_lns` hands out goals with no collision."""
    from mapf_fleet.evaluation.lifelong import lifelong_instances, lifelong_runs, rollout
    from mapf_fleet.evaluation.policies import HeuristicBatchPolicy

    lifelong = lifelong_instances("dense", 17, 24, 1, seed=3)
    runs = lifelong_runs(lifelong, 40, "pibt_anchor_swap_lns", seed=3)
    assert isinstance(runs[0].arbiter.shield, LNSShield)
    rollout(HeuristicBatchPolicy(), runs, shielded=True)
    assert runs[0].goals_reached > 0 and runs[0].recorder.collisions == 0




def test_the_executed_tick_swaps_only_for_or_with_a_stuck_agent():
    """The siding case of the swap rule (`test_coordination_pibt_variants`): agent 1 must back
    away and pull agent 0 after it. The `_swap_lns` rule's executed tick asks for that swap only
    when one of the two has spent `LNS_SWAP_STALL` ticks off its goal since it last came closer; its
    rollout (no tick under way) always."""
    from test_coordination_pibt_variants import _parse

    grid = _parse(["#####.#", "......."])
    shield = make_shield("pibt_swap_lns", grid, [(1, 6), (1, 0)])
    current = [1 * 7 + 2, 1 * 7 + 3]
    occupied_now, decided = {c: i for i, c in enumerate(current)}, [-1, -1]

    def partner(stuck):
        shield._stuck = None if stuck is None else np.array(stuck)
        try:
            return shield._swap_partner(1, current[0], current, occupied_now, decided)
        finally:
            shield._stuck = None

    assert partner(None) == 0  # the rollout: the rule's swap
    assert partner([False, False]) == -1  # the executed tick, nobody stuck: no swap
    assert partner([True, False]) == 0 and partner([False, True]) == 0


def test_ticks_on_the_goal_neither_count_nor_start_the_stall_count_again():
    """Two robots whose goals lie in one corridor can push each other off them in turn for ever,
    each back on its goal every few ticks (the published 40x40 instance 93 with 64 agents, below).
    Ticks on the goal must not start the count again, or neither is ever stuck and the executed
    tick never swaps them; a robot resting on its goal is never stuck."""
    grid = np.zeros((1, 6), dtype=np.uint8)
    shield = make_shield("pibt_anchor_swap_lns", grid, [(0, 2), (0, 5)])
    rows = [shield.distances.row(2), shield.distances.row(5)]
    counts = []
    # agent 0 reaches its goal, is pushed off, back on, off again ...; agent 1 rests on its goal
    for cell in (3, 2, 3, 2, 3, 4, 3, 2, 3, 3):
        counts.append(shield._stalled(np.array([cell, 5]), rows).tolist())
    assert [c[0] for c in counts] == [0, 0, 1, 1, 2, 3, 4, 4, 5, 6]
    assert [c[1] for c in counts] == [0] * 10
    shield.set_goals([(0, 0), (0, 5)])  # a new goal starts the count afresh
    assert shield._stalled(np.array([3, 5]), [shield.distances.row(0), rows[1]]).tolist()[0] == 0


@pytest.mark.slow
@pytest.mark.skipif(not (DEFAULT_TESTSETS / "40length_64agents.npz").is_file(),
                    reason="published test sets absent")
def test_the_published_corridor_that_two_robots_circled_is_solved():
    """Instance 93 of the paper's 40x40 set with 64 agents: under the 16-tick plan two robots
    circled for ever in a corridor holding both their goals (62 of 64 on goal after 256 ticks)
    while the stall count restarted on every visit to a goal."""
    from mapf_fleet.coordination.plan import distance_rankings
    from mapf_fleet.evaluation.protocol import Scenario, scenario_instances

    inst = scenario_instances(Scenario("40x40", 64, 256, 40, "40length_{agents}agents.npz"), 94)
    grid, goals = np.asarray(inst.maps[93]), np.asarray(inst.goals[93])
    shield = make_shield("pibt_anchor_swap_lns", grid, goals)
    positions = np.asarray(inst.starts[93])
    for _ in range(256):
        positions = shield.step(positions, distance_rankings(shield, positions)).positions
        if (positions == goals).all():
            break
    assert (positions == goals).all(), int((positions != goals).any(axis=1).sum())


@pytest.mark.parametrize("case", range(4))
def test_swap_lns_gets_two_agents_past_each_other_in_every_corridor(case):
    """The swap rule's corridors with a siding, which the anchored PIBT never solves and neither
    does its plan without swap (`pibt_anchor_lns`): the `_swap_lns` rules get through every one
    (the stuck pair swaps)."""
    from test_coordination_pibt_variants import CORRIDORS

    rows, starts, goals, _ = CORRIDORS[case]
    assert _solve("pibt_anchor_lns", rows, starts, goals) is None
    for rule in ("pibt_swap_lns", "pibt_anchor_swap_lns"):
        assert _solve(rule, rows, starts, goals) is not None, rule



def test_a_parsed_rule_reads_the_window_when_asked(monkeypatch):
    """The window is read when a shield is built, as the repairs are: a rule parsed before the
    constant changed plans with the new window."""
    from mapf_fleet.coordination import rules

    rule = Rule.parse("pibt_anchor_swap_lns")
    monkeypatch.setattr(rules, "LNS_WINDOW", 3)
    grid = np.zeros((6, 6), dtype=np.uint8)
    shield = make_shield(rule, grid, np.array([[0, 0], [5, 5]]))
    assert rule.window == 3 and shield.window == 3
