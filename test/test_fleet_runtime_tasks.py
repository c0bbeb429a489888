"""Tasks given while a fleet runs (issue 40, items 4 and 6): a request of several tasks is
queued whole or not at all, naming the bad task by its index in the request; a task file's YAML
syntax error names the file and line; `any` tasks are served under the lifelong source (the
next robot to reach its goal takes them) and refused at once under the instance source, and a
run never succeeds while a task it accepted is still queued."""

from __future__ import annotations

import numpy as np
import pytest

from mapf_fleet.fleet.run import FleetRun
from mapf_fleet.fleet.tasks import (ExternalTasks, InstanceTasks, LifelongTasks, Task,
                                    TaskFileError, load_task_file)

from test_fleet_run import OPEN, distance_decisions


def test_a_request_with_one_bad_task_queues_none_and_names_the_bad_ones_index():
    run = FleetRun(OPEN, np.array([[0, 0], [5, 5]]), ExternalTasks(), rule="pibt", max_steps=0)
    good, bad = Task(((0, 3),), None, "good"), Task(((9, 9),), None, "bad")
    events = run.submit_tasks([good, bad])
    assert [e.event for e in events] == ["rejected", "rejected"]
    assert "off the 6x6 map" in events[1].reason
    assert "task 1 of this request was rejected" in events[0].reason
    assert not run.queue
    run.apply_requests()
    assert not run.active.any()  # the good task did not run
    # sent again after the fix: each task queued once, so the good one runs once
    events = run.submit_tasks([good, Task(((3, 3),), None, "fixed")])
    assert [e.event for e in events] == ["queued", "queued"] and len(run.queue) == 2
    for _ in range(12):
        run.step(distance_decisions(run))
    reached = [e["goal_id"] for e in run.recorder.record["goal_events"] if e["event"] == "reached"]
    assert sorted(reached) == ["fixed", "good"]


def test_a_yaml_syntax_error_in_a_task_file_names_the_file_and_line(tmp_path):
    path = tmp_path / "tasks.yaml"
    path.write_text("- goal: [1, 2]\n- goal: [3, 4\n- goal: [5, 6]\n")
    with pytest.raises(TaskFileError) as info:
        load_task_file(str(path))
    text = str(info.value)
    assert text.startswith(f"{path}:3:") and "not valid YAML" in text and "\n" not in text


def test_an_any_task_during_a_lifelong_run_goes_to_the_next_robot_that_arrives():
    starts, goals = np.array([[0, 0], [5, 5]]), np.array([[0, 3], [5, 1]])
    run = FleetRun(OPEN, starts, LifelongTasks(grid=OPEN, seed=0), goals, rule="pibt",
                   max_steps=40)
    assert run.submit_task(Task(((3, 3),), None, "any-1", "submit_tasks")).event == "queued"
    named = Task(((2, 4),), 1, "for-1", "submit_tasks")
    assert run.submit_task(named).event == "queued"
    while not run.finished():
        run.step(distance_decisions(run))
    events = run.recorder.record["goal_events"]
    served = {e["goal_id"]: e["robot"] for e in events if e["event"] == "reached"
              and e["goal_id"] in ("any-1", "for-1")}
    assert set(served) == {"any-1", "for-1"} and served["for-1"] == 1
    assert not run.queue and run.finish()["success"]


def test_a_lifelong_run_with_a_task_still_queued_at_the_end_is_no_success():
    run = FleetRun(OPEN, np.array([[0, 0]]), LifelongTasks(grid=OPEN, seed=0),
                   np.array([[0, 5]]), rule="pibt", max_steps=2)
    # a cell the robot's own next goal keeps it away from for two ticks: still queued
    run.submit_task(Task(((5, 5),), None, "late", "submit_tasks"))
    while not run.finished():
        run.step(distance_decisions(run))
    outcome = run.finish()
    assert run.queue and not outcome["success"] and "1 queued" in outcome["summary"]


def test_tasks_during_an_instance_run_are_refused_at_once_with_the_reason():
    run = FleetRun(OPEN, np.array([[0, 0], [5, 5]]), InstanceTasks(),
                   np.array([[0, 2], [5, 3]]), rule="pibt", max_steps=20)
    for robot in (None, 1):
        event = run.submit_task(Task(((3, 3),), robot, "t", "submit_tasks"))
        assert event.event == "rejected" and "instance source" in event.reason
        assert "goal R --cell" in event.reason
    assert not run.queue
    # a goal for a named robot still works: it replaces the instance goal
    assert run.request_goal(0, (3, 3), "navigate_to_pose").event == "accepted"
