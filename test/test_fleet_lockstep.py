"""The lockstep bookkeeping shared by the simulator and the aggregator, without ROS: stale and
bad moves, the timeout that turns a missing move into "stay", late moves dropped at the next
tick, readiness, and the run record / outcome texts."""

from __future__ import annotations

import json
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from mapf_fleet.coordination.rules import FLEET_RULE
from mapf_fleet.fleet.run import FleetRun
from mapf_fleet.fleet.tasks import InstanceTasks
from mapf_fleet.fleet.lockstep import FleetTicker


def _move(robot, action, tick=0, episode=9, requested=(), received=0, missing=()):
    return SimpleNamespace(episode=episode, tick=tick, robot_id=robot, action=action,
                           requested=list(requested), messages_received=received,
                           missing_peers=list(missing))


def test_collect_takes_current_moves_and_reports_missing_after_timeout():
    ticker = FleetTicker(3, episode=9)
    assert ticker.on_move(_move(0, 2, requested=[1], received=2)) is None
    assert ticker.on_move(_move(1, 4, tick=1)) is None          # a future tick: ignored
    assert ticker.on_move(_move(1, 4, episode=8)) is None       # another run: ignored
    assert "bad move" in ticker.on_move(_move(2, 7))
    assert "without peers [0]" in ticker.on_move(_move(1, 3, missing=[0]))
    started = time.monotonic()
    decisions = ticker.collect(0.2)
    assert time.monotonic() - started >= 0.15                   # it waited for robot 2
    assert decisions.tick == 0 and decisions.missing == [2]
    np.testing.assert_array_equal(decisions.actions, [2, 3, 0])
    assert decisions.requested == [[1], [], []] and decisions.messages == [2, 0, 0]


def test_collect_returns_as_soon_as_all_moves_are_in_and_late_moves_are_dropped():
    ticker = FleetTicker(2, episode=9, tick=5)
    timer = threading.Timer(0.05, lambda: [ticker.on_move(_move(i, 1, tick=5)) for i in (0, 1)])
    timer.start()
    started = time.monotonic()
    decisions = ticker.collect(600.0)
    # far below the timeout, whatever the machine's load: it did not wait for it
    assert time.monotonic() - started < 300.0 and decisions.missing == []
    ticker.on_move(_move(0, 4, tick=5))   # late for tick 5 (the aggregator still waits)
    assert ticker.advance() == 6
    assert ticker.collect(0.01).missing == [0, 1]


def test_wait_ready_needs_every_robot_hearing_every_peer():
    ticker = FleetTicker(2, episode=1)
    ticker.on_status(SimpleNamespace(robot_id=0, ready=True, peers=2))
    ticker.on_status(SimpleNamespace(robot_id=1, ready=True, peers=1))
    assert ticker.wait_ready(0.05) == [1]
    ticker.on_status(SimpleNamespace(robot_id=1, ready=True, peers=2))
    assert ticker.wait_ready(0.05, also=lambda: False) == []
    assert ticker.wait_ready(5.0) == []


def test_run_records_counts_and_summarises(tmp_path):
    goals = np.array([[0, 1], [2, 2]])
    run = FleetRun(np.zeros((3, 3)), [[0, 0], [2, 2]], InstanceTasks(), goals, max_steps=4,
                   episode=9, series=("rejected",))
    ticker = FleetTicker(2, episode=9)
    ticker.on_move(_move(0, 4))
    decisions = ticker.collect(0.01)
    with pytest.raises(ValueError, match="series"):
        run.advance(decisions, [[0, 1], [2, 2]], [4, 0], collisions=0)
    run = FleetRun(np.zeros((3, 3)), [[0, 0], [2, 2]], InstanceTasks(), goals, max_steps=4,
                   episode=9, series=("rejected",))
    run.advance(decisions, [[0, 1], [2, 2]], [4, 0], collisions=1, rejected=[1])
    progress = run.progress(decisions.missing)
    assert progress["tick"] == 1 and progress["on_goal"] == 2
    assert progress["missed_decisions"] == 1 and progress["missed_robots"] == [1]
    assert run.finished() == "every robot on its goal"
    outcome = run.finish(extra=", 1 rejected poses")
    assert outcome["success"] and outcome["steps"] == 1 and outcome["collisions"] == 1
    assert outcome["summary"] == ("success: 2/2 robots on goal after 1 step, 1 collision, "
                                  "1 missed decision (robots [1]), 0 overridden moves "
                                  f"({FLEET_RULE}), 1 rejected poses")
    run.recorder.write(tmp_path / "run.json")
    record = json.loads((tmp_path / "run.json").read_text())
    assert record["positions"] == [[[0, 0], [2, 2]], [[0, 1], [2, 2]]]
    assert record["actions"] == [[4, 0]] and record["missed"] == [[1]]
    assert record["rejected"] == [[1]]


def test_a_checkpointed_record_says_it_is_incomplete_until_the_outcome(tmp_path):
    run = FleetRun(np.zeros((3, 3)), [[0, 0]], InstanceTasks(), [[2, 2]], max_steps=9)
    ticker = FleetTicker(1, episode=0)
    ticker.on_move(_move(0, 2, episode=0))
    run.advance(ticker.collect(0.01), [[1, 0]], [2])
    run.recorder.checkpoint(tmp_path / "run.json", run.tick)
    record = json.loads((tmp_path / "run.json").read_text())
    assert record["incomplete"] and record["steps"] == 1 and not record["success"]
    assert record["summary"].startswith("incomplete: the run's record stops at tick 1")
    run.finish(stopped_at=1)
    run.recorder.write(tmp_path / "run.json")
    record = json.loads((tmp_path / "run.json").read_text())
    assert "incomplete" not in record and record["summary"].startswith("stopped at tick 1")
