"""EPIBT, the `_epibt` rules (`coordination.epibt`): the rule names, the operations, the safety
guarantees of the PIBT rules for every EPIBT rule (the tick is `PIBTShield.step`), the plan's own
conflict-freeness over the horizon, what the horizon buys (a corridor one-step PIBT enters from
both ends), the cost bound, and the callers (fleet core, evaluator)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapf_fleet.coordination import epibt
from mapf_fleet.coordination.epibt import EPIBTShield, operations
from mapf_fleet.coordination.factory import make_shield
from mapf_fleet.coordination.pibt import PIBTShield
from mapf_fleet.coordination.rules import (CONFLICT_RULES, EPIBT_HORIZON, EPIBT_RULES,
                                           PIBT_RULES, Rule)
from mapf_fleet.grid.actions import ACTION_DELTAS
from mapf_fleet.grid.env import resolve_moves
from mapf_fleet.grid.instance import generate_instance

from test_coordination_pibt_variants import assert_safe, crowded_tick, distance_rankings

EPIBT_OPTIONS = [Rule.parse(rule).pibt_options() for rule in EPIBT_RULES]


# --- names ---------------------------------------------------------------------------------------
def test_epibt_rule_names_parse_build_and_reach_the_callers():
    assert EPIBT_RULES == ("pibt_epibt", "pibt_anchor_epibt", "pibt_swap_epibt",
                           "pibt_anchor_swap_epibt", "pibt_patient_epibt",
                           "pibt_patient_swap_epibt")
    assert set(EPIBT_RULES) <= set(CONFLICT_RULES) and not set(EPIBT_RULES) & set(PIBT_RULES)
    grid = np.zeros((4, 4), dtype=np.uint8)
    goals = np.array([[0, 0], [3, 3]])
    for name in EPIBT_RULES:
        rule = Rule.parse(name)
        assert rule.is_pibt and rule.coordinated and rule.epibt
        assert rule.horizon == EPIBT_HORIZON == 3
        plain = Rule.parse(name.removesuffix("_epibt"))
        assert rule.pibt_options() == plain.pibt_options() and not plain.epibt
        assert Rule.pibt(**rule.pibt_options(), epibt=True) == rule
        assert rule.default_ranking == plain.default_ranking
        shield = make_shield(name, grid, goals)
        assert isinstance(shield, EPIBTShield) and shield.horizon == EPIBT_HORIZON
        assert {o: getattr(shield, o) for o in rule.pibt_options()} == rule.pibt_options()
    assert type(make_shield("pibt_anchor_swap", grid, goals)) is PIBTShield
    for bad in ("pibt_hindrance_epibt", "pibt_epibt_swap", "epibt", "lacam_epibt",
                "pibt_anchor_swap_epibt3"):
        with pytest.raises(ValueError, match=f"conflict rule must be one of .*got '{bad}'"):
            Rule.parse(bad)
    with pytest.raises(ValueError, match="hindrance"):
        EPIBTShield(grid, goals, hindrance=True)

    from mapf_fleet.evaluation.cli import build_parser as evaluate_parser
    from mapf_fleet.evaluation.lifelong import build_parser as lifelong_parser
    from mapf_fleet.fleet.arbiter import check_conflict_rule

    assert evaluate_parser().parse_args(["--conflict-rule", *EPIBT_RULES]).conflict_rule == \
        list(EPIBT_RULES)
    assert lifelong_parser().parse_args(["--lifelong", "--conflict-rule",
                                         *EPIBT_RULES]).conflict_rule == list(EPIBT_RULES)
    assert check_conflict_rule("pibt_anchor_swap_epibt") == "pibt_anchor_swap_epibt"


def test_operations_are_the_moves_without_a_step_back():
    ops = operations(3)
    assert ops.shape == (85, 3) and (ops[0] == 0).all()
    assert len({tuple(o) for o in ops.tolist()}) == len(ops)
    for op in ops.tolist():
        cells = [(0, 0)]
        for a in op:
            if a:
                dr, dc = ACTION_DELTAS[a]
                cells.append((cells[-1][0] + dr, cells[-1][1] + dc))
        assert len(set(cells)) == len(cells), op  # waits aside, every cell once
    assert [len(operations(h)) for h in (1, 2)] == [5, 21]
    with pytest.raises(ValueError, match="horizon must be >= 1"):
        operations(0)


# --- safety --------------------------------------------------------------------------------------
@settings(max_examples=80, deadline=None)
@given(crowded_tick(), st.integers(0, len(EPIBT_RULES) - 1),
       st.sampled_from(["random", "distance", "mixed"]), st.booleans())
def test_no_conflict_for_any_epibt_rule(tick, which, rankings, with_reserved):
    """As the PIBT rules' property test: random maps (up to full), random / distance / mixed
    rankings, fixed agents, reserved cells, several ticks: never two agents in one cell, never
    two trading cells, never an obstacle, the edge or a jump; fixed agents stay; reserved cells
    stay free; the environment finds nothing to revert."""
    grid, positions, goals, fixed, rng = tick
    shield = EPIBTShield(grid, goals, **EPIBT_OPTIONS[which])
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
        result = shield.step(positions, prefs, fixed=fixed, reserved=reserved)
        assert_safe(grid, positions, result.positions, fixed, reserved)
        assert (ACTION_DELTAS[result.actions] == result.positions - positions).all()
        _, collided = resolve_moves(grid, positions, result.actions)
        assert not collided.any()
        # overridden: against the agent's own first choice; held agents (fixed, or standing on
        # a reserved cell) never
        held = fixed | np.array([tuple(p) in set(reserved) for p in positions.tolist()])
        assert (result.overridden == ((result.actions != prefs[:, 0]) & ~held)).all()
        positions = result.positions


def _assert_plan_conflict_free(grid, positions, plan, held, reserved=()):
    h, w = np.asarray(grid).shape
    blocked = (np.asarray(grid) != 0).ravel()
    now = positions[:, 0] * w + positions[:, 1]
    assert (plan[:, 0] == now).all()
    for t in range(1, plan.shape[1]):
        assert not blocked[plan[:, t]].any()
        r0, c0 = np.divmod(plan[:, t - 1], w)
        r1, c1 = np.divmod(plan[:, t], w)
        assert (np.abs(r1 - r0) + np.abs(c1 - c0) <= 1).all(), "a jump"
        assert len(set(plan[:, t].tolist())) == len(plan), f"two agents in one cell at step {t}"
        at = {c: i for i, c in enumerate(plan[:, t - 1].tolist())}
        for i, c in enumerate(plan[:, t].tolist()):
            j = at.get(c, -1)
            assert j < 0 or j == i or plan[j, t] != plan[i, t - 1], f"{i}, {j} trade at step {t}"
        for r, c in reserved:
            k = r * w + c
            assert all(plan[i, t] != k or now[i] == k for i in range(len(plan)))
    assert (plan[held] == plan[held, :1]).all(), "a held agent planned to move"


@settings(max_examples=60, deadline=None)
@given(crowded_tick(), st.integers(0, len(EPIBT_RULES) - 1), st.sampled_from([1, 2, 3, 4]),
       st.booleans())
def test_the_plan_is_conflict_free_over_the_whole_horizon(tick, which, horizon, tight):
    """EPIBT's own search (`plan`): every agent's operation meets no other at any step of the
    horizon (no shared cell, no trade), stays on free cells, one cell a step, held agents wait;
    also when the cost bound cuts the search short (`tight`: a budget of one try an agent)."""
    grid, positions, goals, fixed, rng = tick
    shield = EPIBTShield(grid, goals, **EPIBT_OPTIONS[which], horizon=horizon)
    prefs = distance_rankings(shield, positions)
    old = epibt.TRIES_PER_AGENT
    epibt.TRIES_PER_AGENT = 1 if tight else old
    try:
        plan = shield.plan(positions, prefs, fixed=fixed)
    finally:
        epibt.TRIES_PER_AGENT = old
    assert plan.shape == (len(positions), horizon + 1)
    _assert_plan_conflict_free(grid, positions, plan, fixed)


def test_long_runs_on_generated_maps_stay_safe_and_bounded():
    """Crowded generated maps, 30 ticks each, distance rankings with some random ones and a few
    held agents: safe at every tick, and the search never tries more operations than its bound."""
    for seed, which in zip(range(6), range(len(EPIBT_RULES))):
        inst = generate_instance(12, 40, 0.3, seed)
        grid = np.asarray(inst.grid)
        shield = EPIBTShield(grid, inst.goals, **EPIBT_OPTIONS[which])
        rng = np.random.default_rng(seed)
        positions = np.asarray(inst.starts)
        for _ in range(30):
            n = len(positions)
            prefs = distance_rankings(shield, positions)
            noisy = rng.random(n) < 0.25
            for i in np.flatnonzero(noisy):
                prefs[i] = rng.permutation(5)
            fixed = rng.random(n) < 0.05
            result = shield.step(positions, prefs, fixed=fixed)
            assert_safe(grid, positions, result.positions, fixed)
            assert shield.tries <= epibt.TRIES_PER_AGENT * n  # the pushes taken
            positions = result.positions


# --- what the horizon buys -----------------------------------------------------------------------
CORRIDOR = ["......",
            "##.###",
            "##.###",
            "##.###",
            "......"]


def _solve(rule, rows, starts, goals, limit=60):
    grid = np.array([[c == "#" for c in row] for row in rows], dtype=np.uint8)
    shield = make_shield(rule, grid, goals)
    positions = np.array(starts)
    for tick in range(limit):
        if (positions == shield.goals).all():
            return tick
        positions = shield.step(positions, distance_rankings(shield, positions)).positions
        assert len({tuple(p) for p in positions.tolist()}) == len(positions)
    return None


@pytest.mark.parametrize("rule", ["pibt", "pibt_anchor_swap"])
def test_epibt_crosses_a_corridor_that_one_step_pibt_enters_from_both_ends(rule):
    """Two agents trade ends of a three-cell corridor. One-step PIBT lets both walk in (each
    entry cell is free), then one backs out the whole way: 19 ticks. Under EPIBT the agent of
    lower priority sees the other's three-step operation through the corridor and steps aside
    first: 9 ticks, for the plain and the fleet's rule alike."""
    starts, goals = [(0, 2), (4, 2)], [(4, 2), (0, 2)]
    one_step = _solve(rule, CORRIDOR, starts, goals)
    horizon = _solve(f"{rule}_epibt", CORRIDOR, starts, goals)
    assert one_step == 19 and horizon == 9


# --- the callers ---------------------------------------------------------------------------------
def test_epibt_rule_runs_through_the_fleet_core_and_the_lifelong_evaluator(tmp_path):
    """A lifelong `FleetRun` under `pibt_anchor_swap_epibt` hands out goals with no collision
    and no reverted move; `evaluate --lifelong` measures the rule beside the plain one."""
    import json

    from mapf_fleet.evaluation.lifelong import lifelong_instances, lifelong_runs, main, rollout
    from mapf_fleet.evaluation.policies import HeuristicBatchPolicy

    lifelong = lifelong_instances("dense", 17, 24, 1, seed=3)
    runs = lifelong_runs(lifelong, 40, "pibt_anchor_swap_epibt", seed=3)
    assert isinstance(runs[0].arbiter.shield, EPIBTShield)
    rollout(HeuristicBatchPolicy(), runs, shielded=True)
    assert runs[0].goals_reached > 0 and runs[0].recorder.collisions == 0

    out = tmp_path / "lifelong.json"
    assert main(["--lifelong", "--conflict-rule", "pibt_anchor_swap", "pibt_anchor_swap_epibt",
                 "--kinds", "dense", "--sizes", "17", "--agents", "24", "--instances", "1",
                 "--steps", "30", "--guidance", "none", "--json", str(out), "--quiet"]) == 0
    rows = json.loads(out.read_text())
    rows = rows["results"] if isinstance(rows, dict) else rows
    policies = [row["policy"] for row in rows]
    assert any("epibt" in p for p in policies) and len(policies) == 2
    assert all(row["collisions"] == 0 for row in rows if "collisions" in row)


def test_the_dagger_expert_asks_the_rollouts_own_arbiter():
    """The committed expert asks "what would the rule let through" of the rollout's arbiter: an
    `_epibt` rule's is EPIBT's (it was plain PIBT's, a different tick, before)."""
    from mapf_fleet.training.dagger.expert import CommittedExpert

    grid = np.zeros((5, 5), dtype=np.uint8)
    goals = [(0, 0), (4, 4)]
    assert isinstance(CommittedExpert(grid, goals, rule="pibt_anchor_swap_epibt").rule,
                      EPIBTShield)
    assert type(CommittedExpert(grid, goals, rule="pibt_anchor_swap").rule) is PIBTShield
