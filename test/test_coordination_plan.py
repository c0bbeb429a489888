"""The plan keeper (`lacam` conflict rule) and the committed expert: safe steps for any input,
the plan kept until something leaves it, repairs and fallbacks counted, the rule wired into the
shield factory, the arbiter, the evaluator and the lifelong rollout."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapf_fleet.coordination.lacam import check_plan
from mapf_fleet.coordination.factory import make_shield
from mapf_fleet.coordination.pibt import PIBTShield
from mapf_fleet.coordination.plan import PlanKeeper, distance_rankings
from mapf_fleet.training.dagger.expert import CommittedExpert
from mapf_fleet.fleet.arbiter import TickArbiter, plan_robot_commands, unsafe_commands
from mapf_fleet.grid.instance import generate_instance


@st.composite
def fleet_state(draw):
    size = draw(st.integers(3, 7))
    density = draw(st.sampled_from([0.0, 0.1, 0.3]))
    rng = np.random.default_rng(draw(st.integers(0, 100_000)))
    grid = rng.random((size, size)) < density
    free = np.argwhere(~grid)
    if len(free) < 2:
        grid[:] = False
        free = np.argwhere(~grid)
    n = draw(st.integers(1, len(free)))  # up to a full map
    cells = free[rng.permutation(len(free))[:n]]
    goals = free[rng.permutation(len(free))[:n]]
    return grid, cells, goals, rng


@settings(max_examples=120, deadline=None)
@given(fleet_state(), st.integers(1, 6), st.sampled_from([0.0, 0.2]), st.booleans(),
       st.sampled_from([1e-6, 0.2]))
def test_every_commanded_step_is_safe(state, steps, held_rate, reserve, budget):
    """Random maps up to full, random rankings, held robots, reserved cells, goal changes and
    robots the arbiter's output did not move: every tick passes the arbiter's real-robot check
    (one cell, no shared cell, no swap, held robots held, reserved cells free), planned or
    fallen back (a budget of 1 us forces fallbacks)."""
    grid, positions, goals, rng = state
    keeper = PlanKeeper(grid, goals, planning_budget=budget, max_nodes=2000)
    n = len(positions)
    for _ in range(steps):
        prefs = np.stack([rng.permutation(5) for _ in range(n)])
        held = rng.random(n) < held_rate
        reserved = []
        if reserve:
            occupied = {tuple(p) for p in positions.tolist()}
            free = [tuple(c) for c in np.argwhere(~grid).tolist() if tuple(c) not in occupied]
            if free:
                reserved = [free[rng.integers(len(free))]]
        step = keeper.step(positions, prefs, fixed=held, reserved=reserved)
        assert unsafe_commands(grid, positions, step.positions, held, reserved) == []
        if rng.random() < 0.3:  # a robot missed its command: it stayed
            lagging = rng.integers(n)
            nxt = step.positions.copy()
            nxt[lagging] = positions[lagging]
            if len({tuple(p) for p in nxt.tolist()}) == n and not unsafe_commands(
                    grid, positions, nxt):
                step = type(step)(nxt, step.actions, step.overridden)
        positions = step.positions
        if rng.random() < 0.2:
            goals = np.argwhere(~grid)[rng.permutation(int((~grid).sum()))[:n]]
            keeper.set_goals(goals)


def _run(keeper, inst, ticks=200, rankings=None):
    positions = inst.starts.copy()
    for t in range(ticks):
        prefs = distance_rankings(keeper, positions) if rankings is None else rankings(positions)
        positions = keeper.step(positions, prefs).positions
        if (positions == keeper.goals).all():
            return t + 1, positions
    return None, positions


def test_keeps_one_plan_when_nothing_leaves_it():
    inst = generate_instance(16, 32, 0.2, np.random.default_rng(2))
    keeper = PlanKeeper(inst.grid, inst.goals, planning_budget=5.0)
    steps, _ = _run(keeper, inst)
    assert steps is not None
    stats = keeper.stats()
    assert stats["planner_calls"] == 1 and stats["fallback_ticks"] == 0
    assert stats["planned_ticks"] == steps


def test_the_kept_plan_is_executed_step_by_step():
    inst = generate_instance(12, 16, 0.2, np.random.default_rng(4))
    keeper = PlanKeeper(inst.grid, inst.goals, planning_budget=5.0)
    positions = inst.starts.copy()
    keeper.step(positions, distance_rankings(keeper, positions))
    plan = keeper.plan.copy()
    assert check_plan(inst.grid, plan, inst.starts, inst.goals) == []
    positions = plan[1]
    for t in range(1, len(plan) - 1):
        assert np.array_equal(keeper.remaining_plan(), plan[t:])
        positions = keeper.step(positions, distance_rankings(keeper, positions)).positions
        assert np.array_equal(positions, plan[t + 1])


def test_repairs_when_a_robot_leaves_the_plan_or_a_goal_changes():
    inst = generate_instance(12, 12, 0.1, np.random.default_rng(5))
    keeper = PlanKeeper(inst.grid, inst.goals, planning_budget=5.0)
    positions = inst.starts.copy()
    positions = keeper.step(positions, distance_rankings(keeper, positions)).positions
    # a robot did not move as commanded: undo one robot's move (if it moved)
    moved = np.flatnonzero((positions != inst.starts).any(axis=1))
    drift = positions.copy()
    drift[moved[0]] = inst.starts[moved[0]]
    if len({tuple(p) for p in drift.tolist()}) == len(drift):
        keeper.step(drift, distance_rankings(keeper, drift))
        assert keeper.stats()["repairs_off_plan"] == 1
        assert keeper.stats()["planner_calls"] == 2
        positions = keeper.plan[1]
    calls = keeper.stats()["planner_calls"]
    goals = keeper.goals.copy()
    goals[0] = positions[0]  # robot 0's new goal: where it stands
    if len({tuple(g) for g in goals.tolist()}) == len(goals):
        assert keeper.set_goals(goals)[0]
        keeper.step(positions, distance_rankings(keeper, positions))
        assert keeper.stats()["planner_calls"] == calls + 1
        assert (keeper.plan[-1] == goals).all()


def test_a_held_robot_the_plan_moves_triggers_a_repair_that_holds_it():
    inst = generate_instance(12, 12, 0.1, np.random.default_rng(6))
    keeper = PlanKeeper(inst.grid, inst.goals, planning_budget=5.0)
    positions = inst.starts.copy()
    keeper.step(positions, distance_rankings(keeper, positions))
    positions = keeper.plan[1]
    nxt = keeper.plan[2]
    mover = int(np.flatnonzero((nxt != positions).any(axis=1))[0])
    held = np.zeros(len(positions), dtype=bool)
    held[mover] = True
    step = keeper.step(positions, distance_rankings(keeper, positions), fixed=held)
    assert (step.positions[mover] == positions[mover]).all()
    assert keeper.stats()["repairs_held"] == 1
    assert unsafe_commands(inst.grid, positions, step.positions, held) == []


def test_no_plan_in_the_budget_falls_back_to_the_anchored_pibt_step():
    inst = generate_instance(12, 20, 0.2, np.random.default_rng(8))
    keeper = PlanKeeper(inst.grid, inst.goals, planning_budget=1e-9)
    shield = PIBTShield(inst.grid, inst.goals, anchor=True)
    positions = inst.starts.copy()
    rng = np.random.default_rng(0)
    for _ in range(5):
        prefs = np.stack([rng.permutation(5) for _ in range(len(positions))])
        a = keeper.step(positions, prefs)
        b = shield.step(positions, prefs)
        assert np.array_equal(a.positions, b.positions)
        assert np.array_equal(keeper.priorities, shield.priorities)
        positions = a.positions
    assert keeper.stats()["fallback_ticks"] == 5 and keeper.stats()["fallback_rate"] == 1.0


def test_the_fallback_rule_must_be_anchored():
    inst = generate_instance(10, 4, 0.1, np.random.default_rng(2))
    assert PlanKeeper(inst.grid, inst.goals, fallback_rule="pibt_anchor_swap").fallback.swap
    for rule in ("pibt_swap", "lacam"):
        with pytest.raises(ValueError, match=rule):
            PlanKeeper(inst.grid, inst.goals, fallback_rule=rule)


def test_periodic_replanning_keeps_the_plan_valid():
    inst = generate_instance(12, 16, 0.2, np.random.default_rng(9))
    keeper = PlanKeeper(inst.grid, inst.goals, planning_budget=5.0, replan_every=3)
    steps, _ = _run(keeper, inst)
    assert steps is not None
    assert keeper.stats()["repairs_periodic"] >= 1


def test_the_lacam_rule_everywhere_a_shield_runs():
    inst = generate_instance(10, 8, 0.1, np.random.default_rng(1))
    keeper = make_shield("lacam", inst.grid, inst.goals, planning_budget=0.5)
    assert isinstance(keeper, PlanKeeper) and keeper.planning_budget == 0.5
    # the fleet's rule's swap in the search's successors and in the fallback step
    assert keeper.planner.swap and keeper.fallback.swap and keeper.fallback.anchor
    arbiter = TickArbiter(inst.grid, inst.goals, "lacam", planning_budget=0.25)
    assert arbiter.shield.planning_budget == 0.25
    positions = inst.starts.copy()
    waypoints = positions.copy()
    for _ in range(40):
        prefs = distance_rankings(arbiter.shield, positions)
        cmds = plan_robot_commands(arbiter, positions, waypoints, prefs, missing=[0])
        assert cmds.problems == []
        assert (cmds.waypoints[0] == positions[0]).all()  # robot 0 has no decision: held
        positions = waypoints = cmds.waypoints
    arbiter.boost([1])  # the fleet's boost writes the keeper's priorities
    assert arbiter.shield.priorities[1] == arbiter.shield.priorities.max()


def test_evaluator_runs_the_lacam_shield():
    from mapf_fleet.evaluation.policies import HeuristicBatchPolicy
    from mapf_fleet.evaluation.protocol import InstanceSet
    from mapf_fleet.evaluation.runner import run_decentralized

    made = [generate_instance(12, 16, 0.2, np.random.default_rng(k)) for k in range(3)]
    instances = InstanceSet.from_instances(made, "test")
    stats: list = []
    records = run_decentralized(HeuristicBatchPolicy(), instances, 128, "lacam",
                                planning_budget=2.0, stats=stats)
    assert all(r.success for r in records)
    assert all(r.collisions == 0 for r in records)
    assert len(stats) == 3 and all(s["fallback_ticks"] == 0 for s in stats)


def test_evaluate_cli_refuses_a_bad_planning_budget(capsys):
    from mapf_fleet.evaluation.cli import main

    assert main(["--checkpoint", "heuristic", "--no-references", "--conflict-rule", "lacam",
                 "--planning-budget", "0", "--kinds", "dense", "--instances", "1"]) == 2
    err = capsys.readouterr().err
    assert "--planning-budget must be a positive number of seconds, got 0" in err


def test_lifelong_rollout_under_lacam():
    from mapf_fleet.evaluation.lifelong import lifelong_instances, lifelong_runs, rollout
    from mapf_fleet.evaluation.policies import HeuristicBatchPolicy

    instances = lifelong_instances("dense", 17, 16, 1, 0)
    runs = lifelong_runs(instances, 40, "lacam", 0, planning_budget=1.0)
    rollout(HeuristicBatchPolicy(), runs, shielded=True)
    keeper = runs[0].arbiter.shield
    assert runs[0].goals_reached > 0 and runs[0].recorder.collisions == 0
    assert keeper.stats()["goal_changes"] >= 1  # a new goal on arrival: re-planned


def test_trainers_refuse_lacam():
    from mapf_fleet.training.config import TrainConfig, TrainConfigError
    from mapf_fleet.training.dagger import DaggerConfig, DaggerConfigError

    with pytest.raises(DaggerConfigError, match="conflict_rule.*planning arbiter"):
        DaggerConfig(conflict_rule="lacam")
    with pytest.raises(TrainConfigError, match="conflict_rule.*planning arbiter"):
        TrainConfig(conflict_rule="lacam")


def test_committed_expert_labels_from_one_plan():
    inst = generate_instance(12, 16, 0.2, np.random.default_rng(11))
    expert = CommittedExpert(inst.grid, inst.goals, planning_budget=5.0)
    positions = inst.starts.copy()
    actions = expert.moves(positions)
    plan = expert.trajectory()
    assert check_plan(inst.grid, plan, inst.starts, inst.goals) == []
    from mapf_fleet.grid.actions import ACTION_DELTAS

    # following the labels walks the plan; no re-plan while the states stay on it
    for t in range(1, len(plan)):
        positions = positions + ACTION_DELTAS[actions]
        assert np.array_equal(positions, plan[t])
        actions = expert.moves(positions)
        assert not expert.last["replanned"]
    assert expert.keeper.stats()["planner_calls"] == 1
    assert np.array_equal(expert.trajectory()[0], plan[-1])


def test_committed_expert_replans_when_agents_leave_the_plan():
    inst = generate_instance(12, 16, 0.2, np.random.default_rng(12))
    expert = CommittedExpert(inst.grid, inst.goals, planning_budget=5.0)
    positions = inst.starts.copy()
    expert.moves(positions)
    plan = expert.trajectory()
    # every agent follows the plan except one that stays where it was
    nxt = plan[1].copy()
    movers = np.flatnonzero((plan[1] != plan[0]).any(axis=1))
    for lagging in movers:
        trial = nxt.copy()
        trial[lagging] = plan[0][lagging]
        if len({tuple(p) for p in trial.tolist()}) == len(trial):
            break
    else:
        pytest.skip("no single agent can lag here")
    actions = expert.moves(trial)
    assert expert.last["replanned"] and expert.last["on_plan"] == len(trial) - 1
    new = expert.trajectory()
    assert check_plan(inst.grid, new, trial, inst.goals) == []
    from mapf_fleet.grid.actions import ACTION_DELTAS

    assert np.array_equal(trial + ACTION_DELTAS[actions], new[1])


def test_shared_and_cut_off_goals_still_get_a_plan():
    """Lifelong streams may give two robots one goal cell, and a goal may lie beyond a wall:
    the nearest robot keeps the shared goal, the others head for the nearest free cells, and
    every tick is still planned (no fallback)."""
    grid = np.zeros((5, 7), dtype=bool)
    grid[:, 5] = True  # column 6 is cut off
    starts = np.array([[0, 0], [4, 0], [2, 2]])
    goals = np.array([[2, 3], [2, 3], [0, 6]])
    keeper = PlanKeeper(grid, goals, planning_budget=2.0)
    positions = starts.copy()
    for _ in range(12):
        positions = keeper.step(positions, distance_rankings(keeper, positions)).positions
    assert keeper.stats()["fallback_ticks"] == 0
    assert len({tuple(p) for p in positions.tolist()}) == 3
    assert (positions[0] == [2, 3]).all() or (positions[1] == [2, 3]).all()
    assert not grid[positions[:, 0], positions[:, 1]].any()


def test_regions_without_a_plan_fall_back_alone_and_retries_back_off():
    """Two regions: a corridor where two robots must trade ends (no plan exists) and an open
    room. The room's robots follow their plan to their goals; the corridor's take the anchored
    PIBT step; failed re-plans wait 1, 2, 4, ... ticks, so 40 ticks cost a handful of calls."""
    grid = np.zeros((6, 6), dtype=bool)
    grid[1, :] = True  # row 0 is a corridor cut off from rows 2..5
    starts = np.array([[0, 0], [0, 5], [2, 0], [5, 5], [3, 3]])
    goals = np.array([[0, 5], [0, 0], [5, 5], [2, 0], [4, 1]])
    keeper = PlanKeeper(grid, goals, planning_budget=1.0, max_retry_interval=16)
    positions = starts.copy()
    for _ in range(40):
        before = positions
        positions = keeper.step(positions, distance_rankings(keeper, positions)).positions
        assert unsafe_commands(grid, before, positions) == []
    assert (positions[2:] == goals[2:]).all()
    stats = keeper.stats()
    assert stats["fallback_agent_ticks"] >= 2 * 40 and stats["planner_calls"] <= 8
    assert keeper.unplanned.tolist() == [True, True, False, False, False]


def test_real_robots_with_random_delays_never_share_a_cell_under_lacam():
    """The aggregator's tick with slow robots (the model of test/ros/test_arbiter.py): robots
    still driving are held and their waypoints reserved, some decisions are missing; the
    planning arbiter's commands pass `unsafe_commands` every tick and robots never share a
    cell, while the plan is repaired around the held robots."""
    from mapf_fleet.fleet.arbiter import ready_to_send

    rng = np.random.default_rng(7)
    instance = generate_instance(12, 30, 0.3, 11)
    grid = np.asarray(instance.grid)
    arbiter = TickArbiter(grid, instance.goals, "lacam", planning_budget=0.5)
    n = instance.num_agents
    actual = np.asarray(instance.starts).copy()
    state, waypoints, heading = actual.copy(), actual.copy(), {}
    moved = late_seen = 0
    for _ in range(60):
        missing = [i for i in range(n) if rng.random() < 0.05]
        prefs = np.stack([rng.permutation(5) for _ in range(n)])
        plan = plan_robot_commands(arbiter, state, waypoints, prefs, missing)
        assert plan.problems == []
        late_seen += int(plan.late.sum())
        commanded = plan.waypoints.copy()
        sent = np.zeros(n, dtype=bool)
        for _ in range(int(rng.integers(1, 4 * n))):
            reported = {i: tuple(actual[i]) for i in range(n)}
            for i in ready_to_send(commanded, reported, np.flatnonzero(~sent).tolist()):
                sent[i] = True
                heading[i] = tuple(commanded[i])
            movers = [i for i, cell in heading.items() if tuple(actual[i]) != cell]
            if not movers:
                break
            i = movers[int(rng.integers(len(movers)))]
            if rng.random() < 0.7:
                assert np.abs(np.asarray(heading[i]) - actual[i]).sum() == 1
                actual[i] = heading[i]
                moved += 1
                assert len({tuple(c) for c in actual}) == n, "two robots in one cell"
        unsent = ~sent & ~plan.late
        commanded[unsent] = state[unsent]
        waypoints = commanded
        state = actual.copy()
    stats = arbiter.shield.stats()
    assert moved > 50 and late_seen > 0
    assert stats["repairs_held"] + stats["repairs_off_plan"] > 0 and stats["plans_found"] > 0


def test_committed_expert_replans_when_the_labels_were_not_executed():
    """A shield overrode the labels and nobody moved: the same state again is off the plan
    (labelling it from the same plan index would repeat the same labels forever)."""
    inst = generate_instance(12, 16, 0.2, np.random.default_rng(13))
    expert = CommittedExpert(inst.grid, inst.goals, planning_budget=5.0)
    positions = inst.starts.copy()
    expert.moves(positions)
    assert expert.last["replanned"]
    expert.moves(positions)  # the rollout did not advance
    assert expert.last["replanned"] and expert.keeper.stats()["planner_calls"] == 2


def test_committed_expert_labels_for_the_rule_it_runs_under():
    """Told the rule (`pibt_anchor_swap`, anchor every tick) and given its state at every
    state, the expert's labels are executed by that rule far more often than a plan made
    without it (which the anchored top agent keeps leaving), and every step stays safe."""
    from mapf_fleet.grid.actions import ACTION_DELTAS
    from mapf_fleet.training.dagger.ceiling import ceiling_instances

    instances = ceiling_instances({"kind": "dense", "size": 21, "max_steps": 128}, 48, 3, 0)
    exact = {False: 0, True: 0}
    steps = 40
    for inst in instances:
        for follow in (False, True):
            rule = make_shield("pibt_anchor_swap", inst.grid, inst.goals)
            expert = CommittedExpert(inst.grid, inst.goals, planning_budget=10.0,
                                     max_nodes=50_000, swap=True,
                                     rule="pibt_anchor_swap" if follow else None)
            positions = inst.starts.copy()
            for _ in range(steps):
                actions = expert.moves(positions, rule.snapshot() if follow else None)
                wanted = positions + ACTION_DELTAS[actions]
                rankings = distance_rankings(rule, positions)
                for i, a in enumerate(actions.tolist()):
                    rankings[i] = [a] + [b for b in rankings[i].tolist() if b != a]
                step = rule.step(positions, rankings)
                assert len({tuple(p) for p in step.positions.tolist()}) == len(positions)
                exact[follow] += bool(np.array_equal(step.positions, wanted))
                positions = step.positions
    assert exact[True] >= 0.9 * steps * len(instances)
    assert exact[True] > exact[False]


def test_restarts_keep_the_shortest_of_several_searches():
    """With restarts the keeper runs LaCAM with seeds seed, seed + 1, ... and keeps the plan of
    least makespan: never longer than any one seed's, and valid."""
    from mapf_fleet.coordination.lacam import LaCAM
    from mapf_fleet.training.dagger.ceiling import ceiling_instances

    inst = ceiling_instances({"kind": "maze", "size": 21, "max_steps": 128}, 48, 1, 0)[0]
    lengths = [len(LaCAM(inst.grid, seed=s, swap=True).plan(
        inst.starts, inst.goals, time_limit=30, max_nodes=50_000).positions) for s in range(4)]
    keeper = PlanKeeper(inst.grid, inst.goals, planning_budget=30, max_nodes=50_000, swap=True,
                        restarts=4)
    assert keeper.replan(inst.starts)
    assert len(keeper.plan) == min(lengths) and len(set(lengths)) > 1
    assert check_plan(inst.grid, keeper.plan, inst.starts, inst.goals) == []
    assert keeper.planner.seed == 0
    with pytest.raises(ValueError, match="restarts"):
        PlanKeeper(inst.grid, inst.goals, restarts=0)


def test_shared_budget_restarts_stop_when_the_budget_is_spent(monkeypatch):
    """With `shared_budget` the restarts run in what the earlier searches left of one
    `planning_budget` (the arbiter's re-plan costs at most about the budget); without it each
    search has the whole budget and all of them run. A fake clock: each search takes 0.04 s."""
    import types

    from mapf_fleet.coordination import plan as plan_module

    now = [0.0]
    monkeypatch.setattr(plan_module, "time", types.SimpleNamespace(perf_counter=lambda: now[0]))
    inst = generate_instance(10, 6, 0.1, np.random.default_rng(4))
    limits = {}

    def counted(keeper, name):
        original = keeper.planner.plan

        def plan(*args, **kwargs):
            limits.setdefault(name, []).append(kwargs["time_limit"])
            now[0] += 0.04
            return original(*args, **kwargs)
        keeper.planner.plan = plan
        return keeper

    shared = counted(PlanKeeper(inst.grid, inst.goals, planning_budget=0.1, restarts=8,
                                shared_budget=True, swap=True), "shared")
    each = counted(PlanKeeper(inst.grid, inst.goals, planning_budget=0.1, restarts=8,
                              swap=True), "each")
    assert shared.replan(inst.starts) and each.replan(inst.starts)
    # searches at 0, 0.04 and 0.08 s; at 0.12 s the budget is spent
    assert limits["shared"] == pytest.approx([0.1, 0.06, 0.02])
    assert limits["each"] == [0.1] * 8


def test_restarts_only_while_the_plan_is_long_for_its_distances():
    """`restart_ratio`: a plan within that many times the longest agent's distance ends the
    restarts (lifelong re-plans); a plan longer than it does not; 0 restarts always."""
    inst = generate_instance(12, 8, 0.1, np.random.default_rng(5))

    def searches(ratio):
        keeper = PlanKeeper(inst.grid, inst.goals, planning_budget=10, restarts=4, swap=True,
                            restart_ratio=ratio)
        calls = []
        original = keeper.planner.plan
        keeper.planner.plan = lambda *a, **k: calls.append(1) or original(*a, **k)
        assert keeper.replan(inst.starts)
        makespan = len(keeper.plan) - 1
        return len(calls), makespan / keeper._longest_distance(inst.starts, inst.goals)

    calls, ratio = searches(0.0)
    assert calls == 4
    assert searches(ratio + 0.01)[0] == 1  # the first plan is short enough: no restart
    assert searches(0.5)[0] == 4  # no plan is within half the longest distance
    with pytest.raises(ValueError, match="restart_ratio"):
        PlanKeeper(inst.grid, inst.goals, restart_ratio=-1)


def test_no_restarts_once_the_goals_stream_in_unless_asked():
    """`streamed_restarts=False` (the arbiter): the episode's first goals get every restart; once
    `set_goals` changed them (a lifelong stream), one search per re-plan; a new episode
    (`reset`) restarts again."""
    inst = generate_instance(12, 8, 0.1, np.random.default_rng(6))
    moved = np.roll(inst.goals, 1, axis=0)
    for streamed_restarts, after in ((False, 1), (True, 4)):
        keeper = PlanKeeper(inst.grid, inst.goals, planning_budget=10, restarts=4, swap=True,
                            streamed_restarts=streamed_restarts)
        calls = []
        original = keeper.planner.plan
        keeper.planner.plan = lambda *a, **k: calls.append(1) or original(*a, **k)
        assert keeper.replan(inst.starts) and len(calls) == 4
        keeper.set_goals(moved)
        assert keeper.replan(inst.starts) and len(calls) == 4 + after
        keeper.reset()  # a new episode: its goals are its first ones
        assert keeper.replan(inst.starts) and len(calls) == 8 + after
