"""The fleet core (`mapf_fleet.fleet`): one tick machinery for the simulator, the aggregator and
the evaluator's lifelong rollout; goals and tasks at run time."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mapf_fleet.coordination.pibt import PIBTShield
from mapf_fleet.fleet.record import Decisions
from mapf_fleet.fleet.run import FleetRun
from mapf_fleet.fleet.tasks import (ExternalTasks, InstanceTasks, LifelongTasks, Task,
                                    TaskFileError, TaskListTasks, load_task_file,
                                    make_task_source)
from mapf_fleet.grid.actions import ACTION_DELTAS, STAY
from mapf_fleet.grid.instance import generate_instance

OPEN = np.zeros((6, 6), dtype=np.uint8)


def stay_decisions(run: FleetRun) -> Decisions:
    prefs = np.tile(np.arange(5), (run.num_robots, 1))  # stay first
    return Decisions.complete(run.tick, prefs)


def distance_decisions(run: FleetRun) -> Decisions:
    from mapf_fleet.coordination.ranking import rank_actions, tie_breakers
    from mapf_fleet.evaluation.lifelong import observe_runs

    prefs = rank_actions(observe_runs([run]), mode="distance",
                         ties=tie_breakers(np.arange(run.num_robots), run.tick)[None])[0]
    return Decisions.complete(run.tick, prefs)


def test_instance_run_equals_the_batched_evaluator_under_the_anchor():
    """The one-shot fleet core and the evaluator's runner (env + one PIBTShield) make the same
    moves with plain PIBT's rankings: the simulator's tick machinery is the evaluator's."""
    from mapf_fleet.evaluation.policies import HeuristicBatchPolicy
    from mapf_fleet.evaluation.protocol import InstanceSet
    from mapf_fleet.evaluation.runner import run_decentralized

    made = [generate_instance(12, 10, 0.2, np.random.default_rng(s)) for s in range(3)]
    instances = InstanceSet.from_instances(made, "test")
    records = run_decentralized(HeuristicBatchPolicy(), instances, 64, conflict_rule="pibt_anchor")
    for k, inst in enumerate(made):
        run = FleetRun(inst.grid, inst.starts, InstanceTasks(), inst.goals, rule="pibt_anchor",
                       max_steps=64)
        while not run.finished():
            run.step(distance_decisions(run))
        assert run.steps == records[k].steps
        assert bool(run.on_goal().all()) == records[k].success


def test_lifelong_goals_depend_on_seed_and_robot_only():
    grid = np.zeros((10, 10), dtype=np.uint8)
    grid[5, 2:8] = 1
    a = LifelongTasks(grid=grid, seed=7)
    b = LifelongTasks(grid=grid, seed=7)
    seq_a = [a.next_goal(3, (0, 0)) for _ in range(5)]
    other = [b.next_goal(1, (0, 0)) for _ in range(3)]  # another robot draws first: no effect
    seq_b = [b.next_goal(3, (0, 0)) for _ in range(5)]
    assert seq_a == seq_b
    assert all(grid[c] == 0 and c != (0, 0) for c in seq_a + other)
    assert LifelongTasks(grid=grid, seed=8).next_goal(3, (0, 0)) != seq_a[0] or \
        [LifelongTasks(grid=grid, seed=8).next_goal(3, (0, 0)) for _ in range(1)] != seq_a[:1]


def test_lifelong_run_hands_out_a_new_goal_on_arrival_and_counts_throughput():
    starts = np.array([[0, 0], [5, 5]])
    goals = np.array([[0, 1], [5, 4]])
    run = FleetRun(OPEN, starts, LifelongTasks(grid=OPEN, seed=0), goals, rule="pibt",
                   max_steps=30)
    first = run.goals.copy()
    run.step(distance_decisions(run))
    assert run.goals_reached == 2  # both arrived in one step
    assert (run.goals != first).any(axis=1).all()  # and both got a new goal
    while not run.finished():
        run.step(distance_decisions(run))
    assert run.steps == 30 and run.goals_reached > 4
    assert run.throughput == pytest.approx(run.goals_reached / 30)
    events = run.recorder.record["goal_events"]
    assert sum(e["event"] == "reached" for e in events) == run.goals_reached
    outcome = run.finish()
    assert outcome["success"] and "throughput" in outcome["summary"]


def test_goal_requests_are_checked_and_applied_at_the_next_tick():
    grid = np.zeros((6, 6), dtype=np.uint8)
    grid[2, :] = 1  # row 2 is a wall: rows 3-5 are cut off from rows 0-1
    grid[0, 5] = 1
    run = FleetRun(grid, np.array([[0, 0], [1, 1]]), ExternalTasks(), rule="pibt_anchor",
                   max_steps=0)
    assert run.waiting and not run.active.any()
    assert (run.goals == run.positions).all()  # idle robots' goals are their own cells
    cases = {(9, 0, 0): "unknown robot", (0, 7, 7): "off the 6x6 map",
             (0, 0, 5): "is an obstacle", (0, 4, 4): "unreachable"}
    for (robot, r, c), text in cases.items():
        event = run.request_goal(robot, (r, c), "test")
        assert event.event == "rejected" and text in event.reason
    assert run.request_goal(0, (1, 4), "test", "g1").event == "accepted"
    clash = run.request_goal(1, (1, 4), "test")
    assert clash.event == "rejected" and "robot 0 is already headed" in clash.reason
    assert not run.active.any()  # applied at the tick boundary, not before
    run.apply_requests()
    assert run.active[0] and tuple(run.goals[0]) == (1, 4)
    for _ in range(10):
        run.step(distance_decisions(run))
    assert tuple(run.positions[0]) == (1, 4) and not run.active[0]
    assert run.tasks_done[0] == 1
    kinds = [e["event"] for e in run.recorder.record["goal_events"] if e["goal_id"] == "g1"]
    assert kinds == ["assigned", "reached"]


def test_cancel_holds_the_robot_and_a_new_goal_preempts():
    run = FleetRun(OPEN, np.array([[0, 0]]), ExternalTasks(), rule="pibt", max_steps=0)
    run.request_goal(0, (5, 5), "test", "far")
    run.apply_requests()
    run.step(distance_decisions(run))
    run.request_goal(0, (0, 5), "test", "other")
    events = run.step(distance_decisions(run))[1]
    assert [(e.event, e.goal_id) for e in events] == [("preempted", "far"), ("assigned", "other")]
    assert run.cancel(0, "far").event == "rejected"  # not its goal any more
    assert run.cancel(0, "other").event == "accepted"
    events = run.step(distance_decisions(run))[1]
    assert [e.event for e in events] == ["cancelled"]
    held = run.positions.copy()
    for _ in range(3):
        run.step(distance_decisions(run))
    assert (run.positions == held).all() and not run.active.any()


def test_any_robot_tasks_go_to_the_nearest_idle_robot_by_path_distance():
    grid = np.zeros((5, 9), dtype=np.uint8)
    grid[0:4, 4] = 1  # a wall with a gap at the bottom: robot 1 is near in metres, far by path
    starts = np.array([[0, 0], [0, 5], [4, 8]])
    task = Task(((0, 3), (4, 0)), None, "pick")
    run = FleetRun(grid, starts, TaskListTasks(tasks=[task]), rule="pibt", max_steps=100)
    assert run.active.tolist() == [True, False, False]  # robot 0: 3 steps; robot 1: 11
    while not run.finished():
        run.step(distance_decisions(run))
    assert run.finished() == "every task done"
    assert run.tasks_done.tolist() == [1, 0, 0] and run.goals_reached == 2
    assert run.finish()["success"]


def test_any_robot_tasks_go_to_the_nearest_idle_robot_by_guided_cost():
    """Under guidance the nearest idle robot is the one with the least guided cost, not the
    fewest steps; the choice reads the table's rows (no -1 array made for it)."""
    from mapf_fleet.grid.guidance import Guidance

    grid = np.zeros((3, 7), dtype=np.uint8)
    costs = np.ones((3, 7, 5))
    costs[..., 3] = 5.0  # moving left costs 5: robot 1 is 2 steps away but costs 10, robot 0 4
    starts = np.array([[0, 0], [0, 6]])
    run = FleetRun(grid, starts, ExternalTasks(), rule="pibt", max_steps=0,
                   guidance=Guidance.from_costs(grid, costs))
    run.submit_task(Task(((0, 4),), None, "a", "service"))
    run.apply_requests()
    assert run.active.tolist() == [True, False]
    assert not run.map.table._arrays  # the goal choice read the row itself
    unguided = FleetRun(grid, starts, ExternalTasks(), rule="pibt", max_steps=0)
    unguided.submit_task(Task(((0, 4),), None, "a", "service"))
    unguided.apply_requests()
    assert unguided.active.tolist() == [False, True]


def test_tasks_wait_for_an_idle_robot():
    run = FleetRun(OPEN, np.array([[0, 0]]), ExternalTasks(), rule="pibt", max_steps=0)
    run.submit_task(Task(((0, 3),), None, "a", "service"))
    run.submit_task(Task(((3, 3),), None, "b", "service"))
    run.apply_requests()
    assert tuple(run.goals[0]) == (0, 3) and len(run.queue) == 1
    for _ in range(10):
        run.step(distance_decisions(run))
    assert tuple(run.positions[0]) == (3, 3) and run.tasks_done[0] == 2


def test_set_goals_keeps_the_priority_of_robots_whose_goal_stays():
    shield = PIBTShield(OPEN, np.array([[5, 5], [5, 0]]))
    prefs = np.tile(np.arange(5), (2, 1))
    for _ in range(3):
        shield.step(np.array([[0, 0], [0, 5]]), prefs)
    before = shield.priorities.copy()
    changed = shield.set_goals(np.array([[5, 5], [4, 0]]))
    assert changed.tolist() == [False, True]
    assert shield.priorities[0] == before[0]
    assert shield.priorities[1] == shield.base_priority[1]


def test_max_steps_zero_is_only_for_continuous_sources():
    with pytest.raises(ValueError, match="max_steps"):
        FleetRun(OPEN, np.array([[0, 0]]), InstanceTasks(), np.array([[1, 1]]), max_steps=0)
    with pytest.raises(ValueError, match="max_steps"):
        FleetRun(OPEN, np.array([[0, 0]]), ExternalTasks(), max_steps=-5)


def test_task_files_name_the_file_task_and_field(tmp_path):
    good = tmp_path / "tasks.yaml"
    good.write_text("tasks:\n  - goal: [1, 2]\n  - {pickup: [0, 0], dropoff: [3, 3], robot: 1}\n"
                    "  - {xy: [2.5, 0.5]}\n")
    tasks = load_task_file(str(good), num_robots=2, cell_of=lambda x, y: (int(y), int(x)))
    assert [t.goals for t in tasks] == [((1, 2),), ((0, 0), (3, 3)), ((0, 2),)]
    assert tasks[1].robot == 1
    cases = {"- {goal: [1]}": "task 0: field 'goal'",
             "- {pickup: [1, 1]}": "task 0: missing field 'goal'",
             "- {goal: [1, 1], robot: 5}": "field 'robot': 5",
             "- {goal: [1, 1], speed: 3}": "unknown field 'speed'",
             "tasks: []": "the list is empty",
             "[unclosed": "not valid YAML"}
    for text, message in cases.items():
        bad = tmp_path / "bad.yaml"
        bad.write_text(text + "\n")
        with pytest.raises(TaskFileError, match=message) as info:
            load_task_file(str(bad), num_robots=2)
        assert str(bad) in str(info.value)
    with pytest.raises(ValueError, match="needs a task file"):
        make_task_source("tasks", OPEN)
    with pytest.raises(ValueError, match="task_source must be one of"):
        make_task_source("forever", OPEN)


def test_lifelong_rollout_is_deterministic_and_the_same_for_every_policy_goal_stream():
    from mapf_fleet.evaluation.lifelong import lifelong_instances, lifelong_runs, rollout
    from mapf_fleet.evaluation.policies import HeuristicBatchPolicy

    instances = lifelong_instances("random", 16, 12, 2, seed=3)
    results = []
    for _ in range(2):
        runs = lifelong_runs(instances, 40, "pibt_anchor", seed=3)
        rollout(HeuristicBatchPolicy(), runs, shielded=True)
        results.append([run.recorder.record["positions"] for run in runs])
        assert all(run.goals_reached > 0 for run in runs)
    assert results[0] == results[1]
    # robot 0's goal sequence is the same whatever moves it made: compare two rules
    streams = []
    for rule in ("pibt_anchor", "revert"):
        runs = lifelong_runs(instances.subset([0]), 60, rule, seed=3)
        rollout(HeuristicBatchPolicy(), runs, shielded=rule != "revert")
        streams.append([tuple(e["cell"]) for e in runs[0].recorder.record["goal_events"]
                        if e["robot"] == 0 and e["event"] == "assigned"])
    shortest = min(len(s) for s in streams)
    assert shortest >= 2 and streams[0][:shortest] == streams[1][:shortest]


@pytest.mark.parametrize("rule", ["pibt", "pibt_anchor", "pibt_swap", "pibt_anchor_swap_hindrance"])
def test_an_idle_robot_in_a_dead_end_clears_a_busy_robots_goal(rule):
    """Goal (0, 0) is a dead end whose only way in is (1, 0), and an idle robot stands on it:
    plain PIBT would push it deeper forever (a dead end is on no cycle); the idle robot is sent
    out to the nearest free cell first, with the top priority."""
    grid = np.array([[0, 1, 1, 1],
                     [0, 1, 0, 0],
                     [0, 0, 0, 0]], dtype=np.uint8)
    run = FleetRun(grid, np.array([[0, 0], [2, 0]]), ExternalTasks(), rule=rule, max_steps=0)
    assert run.request_goal(1, (0, 0), "test", "corner").event == "accepted"
    for _ in range(20):
        run.step(distance_decisions(run))
        if not run.active[1]:
            break
    assert run.tasks_done[1] == 1 and tuple(run.positions[1]) == (0, 0)
    assert not run.active[0] and tuple(run.positions[0]) != (0, 0)


# a 5x5 map: cell (4, 4) is free but walled in; robots stand at (0, 0) and (0, 4)
WALLED = np.zeros((5, 5), dtype=np.uint8)
WALLED[3, 3:] = 1
WALLED[4, 3] = 1
WALLED_STARTS = np.array([[0, 0], [0, 4]])


def test_unreachable_task_goals_are_refused_with_file_line_and_task_index(tmp_path):
    cases = {"- {goal: [1, 1]}\n- {goal: [3, 3]}\n": "tasks.yaml:2: task 1: goal (3, 3) is "
                                                      "an obstacle",
             "- {goal: [1, 1]}\n- {goal: [1, 2]}\n- {goal: [4, 4]}\n":
                 "tasks.yaml:3: task 2: goal (4, 4) cannot be reached by any robot",
             "tasks:\n  - {goal: [9, 0]}\n": "tasks.yaml:2: task 0: goal (9, 0) is off the 5x5 "
                                              "map",
             "- {pickup: [1, 1], dropoff: [4, 4]}\n": "task 0: dropoff (4, 4) cannot be reached "
                                                      "from the pickup (1, 1)",
             "- {goal: [0, 0]}\n- {goal: [1, 2], robot: 1}\n- {goal: [4, 4], robot: 0}\n":
                 "tasks.yaml:3: task 2: goal (4, 4) cannot be reached by robot 0"}
    path = tmp_path / "tasks.yaml"
    for text, message in cases.items():
        path.write_text(text)
        with pytest.raises(TaskFileError) as info:
            load_task_file(str(path), num_robots=2, grid=WALLED, starts=WALLED_STARTS)
        assert message in str(info.value), (text, str(info.value))
    # the same file is fine without the map (the run checks it)
    path.write_text("- {goal: [1, 1]}\n- {goal: [2, 2]}\n")
    tasks = load_task_file(str(path), num_robots=2, grid=WALLED, starts=WALLED_STARTS)
    assert [t.task_id for t in tasks] == ["tasks-0", "tasks-1"]


def test_a_submitted_task_no_robot_can_reach_is_rejected_at_once():
    run = FleetRun(WALLED, WALLED_STARTS, ExternalTasks(), rule="pibt", max_steps=0)
    for task, reason in [(Task(((4, 4),)), "cannot be reached by any robot"),
                         (Task(((3, 3),)), "is an obstacle"),
                         (Task(((1, 1), (4, 4))), "cannot be reached from the pickup"),
                         (Task(((7, 0),)), "off the 5x5 map")]:
        event = run.submit_task(task)
        assert event.event == "rejected" and reason in event.reason, (task, event)
    assert not run.queue
    assert run.submit_task(Task(((2, 2),))).event == "queued"
    event = run.request_goal(0, (4, 4), "goal_pose")
    assert event.event == "rejected" and "unreachable" in event.reason


def test_a_killed_run_keeps_every_tick_in_its_journal(tmp_path):
    """The record is written whole only at the first tick and at the end; the journal beside
    it gets every tick as it ends, so a simulator killed (-9) in between loses none, and the
    rate read back is the journal's (ticks over the time of the last one)."""
    import os

    from mapf_fleet.fleet.record import journal_path, read_record

    path = tmp_path / "run.json"
    run = FleetRun(OPEN, np.array([[0, 0], [5, 5]]), LifelongTasks(grid=OPEN, seed=0),
                   np.array([[0, 5], [5, 0]]), rule="pibt", max_steps=0,
                   series=("executed", "overridden"))
    run.recorder.open_journal(path)
    for _ in range(3):
        run.step(distance_decisions(run))
    run.recorder.checkpoint(path, run.tick)  # the last whole rewrite
    for _ in range(4):
        run.step(distance_decisions(run))
    run.recorder._journal.close()  # killed: no final write
    with open(journal_path(path), "a") as f:
        f.write('{"t": 9.9, "steps"')  # the line being written when it died
    record = read_record(path)
    assert record["incomplete"] and record["steps"] == 7, record["summary"]
    assert len(record["positions"]) == 8 and len(record["executed"]) == 7
    assert record["positions"][-1] == run.positions.tolist()
    assert len(record["goal_events"]) == len(run.recorder.record["goal_events"])
    assert 0 < record["run_seconds"] < 9.9
    # finished normally: the record is whole and the journal gone
    run.finish()
    run.recorder.write(path)
    run.recorder.close_journal(path)
    assert not os.path.exists(journal_path(path)) and read_record(path)["steps"] == 7


def test_a_record_written_at_the_first_tick_and_its_journal_rebuild_the_whole_run(tmp_path):
    """As the simulator records: the record written once at the first tick, then only the
    journal; a killed run reads back every tick and goal event the run itself holds."""
    from mapf_fleet.fleet.record import read_record

    path = tmp_path / "run.json"
    inst = generate_instance(12, 10, 0.2, 3)
    run = FleetRun(inst.grid, inst.starts, LifelongTasks(grid=inst.grid, seed=3), inst.goals,
                   max_steps=0, series=("executed", "overridden"))
    run.recorder.open_journal(path)
    run.step(distance_decisions(run))
    run.recorder.checkpoint(path, run.tick)
    for _ in range(40):
        run.step(distance_decisions(run))
    run.recorder._journal.close()  # killed: no final write
    record, whole = read_record(path), run.recorder.record
    assert record["incomplete"] and record["steps"] == 41 and run.goals_reached > 0
    for name in ("positions", "actions", "missed", "executed", "overridden", "goal_events"):
        assert record[name] == whole[name], name


def test_a_streamed_record_holds_no_tick_in_memory_and_writes_the_same_record(tmp_path):
    """The fleet's nodes journal with keep_ticks False: a tick leaves memory once journaled, and
    the record written at the end (streamed from the journal), or read back after a kill, is the
    record of a run that kept every tick in memory."""
    import json

    from mapf_fleet.fleet.record import read_record

    inst = generate_instance(12, 10, 0.2, 3)
    records = []
    for keep in (True, False):
        path = tmp_path / f"run_{keep}.json"
        run = FleetRun(inst.grid, inst.starts, LifelongTasks(grid=inst.grid, seed=3), inst.goals,
                       max_steps=0, series=("executed", "overridden"))
        run.recorder.open_journal(path, keep_ticks=keep)
        run.step(distance_decisions(run))
        run.recorder.checkpoint(path, run.tick)
        for _ in range(30):
            run.step(distance_decisions(run))
        if not keep:  # nothing of the 31 ticks is held, and a kill loses none of them
            assert all(run.recorder.record[k] == [] for k in run.recorder.tick_keys)
            killed = read_record(path)
            assert killed["incomplete"] and len(killed["positions"]) == 32
        run.abort_active("the run ended")  # events after the last tick
        run.finish()
        run.recorder.write(path)
        run.recorder.close_journal(path)
        records.append(json.loads(path.read_text()))
    kept, streamed = records
    assert run.goals_reached > 0 and len(kept["positions"]) == 32
    for record in records:
        record.pop("run_seconds")
    assert kept == streamed
    assert killed["positions"] == kept["positions"] and killed["actions"] == kept["actions"]


@pytest.mark.slow
def test_the_readmes_32_robot_example_is_solved_by_the_fleet_core():
    """README's second example (`up --num-robots 32 --size 24 ...`): its generated instance is
    solved by the fleet's core (FleetRun under the default rule, the shipped policy with the
    ranking it records), as the fleet runs it. On the 16x16 default map two robots end stuck
    in a dead end (docs/fleet.md)."""
    import re
    import shlex
    from pathlib import Path

    from mapf_fleet.coordination.ranking import default_ranking
    from mapf_fleet.evaluation.lifelong import rollout
    from mapf_fleet.evaluation.policies import CheckpointBatchPolicy
    from mapf_fleet.models.checkpoint import load_checkpoint
    from mapf_fleet.ros import launcher

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    line = next(x for x in readme.splitlines() if re.match(r"mapf-fleet up --num-robots 32", x))
    argv = shlex.split(line.split("#")[0])[2:]
    args = launcher.build_parser().parse_args(argv)
    size, density, seed = args.size or 16, args.density or 0.3, args.seed or 0
    checkpoint = launcher.default_checkpoint()
    _, metadata = load_checkpoint(checkpoint)
    inst = generate_instance(size, args.num_robots, density, seed)
    run = FleetRun(inst.grid, inst.starts, InstanceTasks(), inst.goals, rule="pibt_anchor",
                   max_steps=256)
    ranking = default_ranking("pibt_anchor", metadata.get("rankings"))
    rollout(CheckpointBatchPolicy(checkpoint, ranking=ranking), [run], shielded=True)
    assert run.on_goal().all(), f"{int(run.on_goal().sum())}/{run.num_robots} on goal"


def test_steps_to_a_cell_are_cells_whatever_the_guidance():
    """A robot's distance left (the action's feedback) is a length in cells: BFS steps, not the
    guided cost that orders its moves (a step against a highway lane costs more than one)."""
    import numpy as np

    from mapf_fleet.fleet.run import FleetRun
    from mapf_fleet.fleet.tasks import InstanceTasks
    from mapf_fleet.grid.guidance_made import highways
    from mapf_fleet.grid.heuristic import bfs_distances

    grid = np.zeros((9, 9), dtype=np.uint8)
    run = FleetRun(grid, np.array([[0, 0]]), InstanceTasks(), np.array([[8, 8]]),
                   guidance=highways(grid))
    steps = run.map.steps_to((8, 8))
    np.testing.assert_array_equal(steps, bfs_distances(grid, (8, 8)))
    assert (run.map.distance_to((8, 8)) > steps).any()  # the guided costs differ: lanes


@pytest.mark.parametrize("rule", ["pibt_anchor_swap", "pibt_anchor_swap_epibt"])
def test_a_cold_start_in_windows_runs_the_same_lifelong_episode(rule, monkeypatch):
    """The first tick's goals searched in windows (`grid.goal_observer.WINDOW_FROM_BYTES` 0: every
    batch of new goals) and the conflict rule reading them (`DistanceTable.row`'s `WindowRow`)
    give the episode of whole searches, step for step, DCC `default.pt` ranking."""
    from collections import OrderedDict

    from mapf_fleet.evaluation.lifelong import observe_runs
    from mapf_fleet.evaluation.policies import CheckpointBatchPolicy
    from mapf_fleet.grid import goal_observer, heuristic

    checkpoint = Path(__file__).resolve().parents[1] / "models" / "default.pt"
    inst = generate_instance(40, 48, 0.3, 4)

    def episode(window_from: int):
        monkeypatch.setattr(heuristic, "_TABLES", OrderedDict())  # nothing searched before
        monkeypatch.setattr(goal_observer, "WINDOW_FROM_BYTES", window_from)
        run = FleetRun(inst.grid, inst.starts, LifelongTasks(grid=inst.grid, seed=4),
                       inst.goals, rule=rule, max_steps=30)
        policy = CheckpointBatchPolicy(str(checkpoint))
        policy.reset(1, run.num_robots)
        cells, windowed = [], 0
        while not run.finished():
            obs = observe_runs([run], "paper")
            prefs = policy.rank(obs, run.positions[None], run.tick)
            result, _ = run.step(Decisions.complete(run.tick, prefs[0]))
            policy.executed(result.actions[None])
            cells.append(run.positions.copy())
            windowed = max(windowed, heuristic.distance_table(inst.grid).windows.cells)
        return np.stack(cells), windowed, run.goals_reached

    whole, none, reached = episode(1 << 62)
    windows, some, reached_too = episode(0)
    assert none == 0 and some > 0
    np.testing.assert_array_equal(windows, whole)
    assert reached_too == reached > 0
