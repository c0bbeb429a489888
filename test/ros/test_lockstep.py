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

from mapf_fleet.ros.lockstep import FleetTicker, RunRecorder


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


def test_recorder_counts_records_and_summarises(tmp_path):
    goals = np.array([[0, 1], [2, 2]])
    recorder = RunRecorder(9, 2, goals, max_steps=4, series=("rejected",))
    recorder.start([[0, 0], [2, 2]])
    ticker = FleetTicker(2, episode=9)
    ticker.on_move(_move(0, 4))
    decisions = ticker.collect(0.01)
    with pytest.raises(ValueError, match="series"):
        recorder.add_tick(decisions, [[0, 1], [2, 2]], 0)
    progress = recorder.add_tick(decisions, [[0, 1], [2, 2]], 1, rejected=[1])
    assert progress["tick"] == 1 and progress["on_goal"] == 2
    assert progress["missed_decisions"] == 1 and progress["missed_robots"] == [1]
    outcome = recorder.finish([[0, 1], [2, 2]], extra=", 1 rejected poses")
    assert outcome["success"] and outcome["steps"] == 1 and outcome["collisions"] == 1
    assert outcome["summary"] == ("success: 2/2 robots on goal after 1 steps, 1 collisions, "
                                  "1 missed decisions (robots [1]), 1 rejected poses")
    recorder.write(tmp_path / "run.json")
    run = json.loads((tmp_path / "run.json").read_text())
    assert run["positions"] == [[[0, 0], [2, 2]], [[0, 1], [2, 2]]]
    assert run["actions"] == [[4, 0]] and run["missed"] == [[1]] and run["rejected"] == [[1]]
