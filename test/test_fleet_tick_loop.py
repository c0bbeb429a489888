"""The lockstep tick loop without ROS (fleet.tick_loop.TickLoop) on a fake clock: the robots are
an in-memory double that answers each published state with moves, the outlet keeps what the
loop publishes (RecordingOutlet)."""

from __future__ import annotations

import json
import threading
from types import SimpleNamespace

import numpy as np

from mapf_fleet.fleet.lockstep import FleetTicker
from mapf_fleet.fleet.run import FleetRun
from mapf_fleet.fleet.tasks import InstanceTasks
from mapf_fleet.fleet.tick_loop import RecordingOutlet, TickLoop
from mapf_fleet.grid.actions import ACTION_DELTAS, STAY

GRID = np.zeros((1, 5), dtype=np.uint8)  # one row: robot 0 from (0, 0) to (0, 2)


class FakeClock:
    def __init__(self):
        self.now, self.slept = 100.0, []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        self.now += seconds


class Robots(RecordingOutlet):
    """The outlet, and the robots: each state published (not done) gets every robot's move
    toward its goal, but for the robots in `silent`; `on_state(tick)` runs before the moves."""

    def __init__(self, run, ticker, silent=(), on_state=lambda tick: None):
        super().__init__()
        self.run, self.ticker, self.silent, self.on_state = run, ticker, set(silent), on_state

    def publish_state(self, done: bool) -> None:
        super().publish_state(done)
        if done:
            return
        self.on_state(self.ticker.tick)
        for i, (cell, goal) in enumerate(zip(self.run.positions, self.run.goals)):
            if i in self.silent:
                continue
            step = np.sign(np.asarray(goal) - np.asarray(cell))
            action = next((a for a, d in enumerate(ACTION_DELTAS) if tuple(d) == tuple(step)),
                          STAY)
            ranking = [action] + [a for a in range(5) if a != action]
            self.ticker.on_move(SimpleNamespace(
                episode=self.ticker.episode, tick=self.ticker.tick, robot_id=i, action=action,
                preferences=ranking, requested=[], messages_received=0, missing_peers=[]))


def _loop(starts, goals, settings, silent=(), on_state=lambda tick: None, record_file="",
          max_steps=20):
    run = FleetRun(GRID, starts, InstanceTasks(), np.array(goals), max_steps=max_steps,
                   episode=7, series=("executed", "overridden"))
    ticker = FleetTicker(len(starts), episode=7)
    robots = Robots(run, ticker, silent, on_state)
    clock = FakeClock()

    def step(decisions):
        result, events = run.step(decisions)
        ticker.advance()
        return events, result.overridden_ids

    loop = TickLoop(run, ticker, step, robots, lock=threading.RLock(), settings=settings,
                    record_file=record_file, clock=clock, sleep=clock.sleep)
    return loop, robots, clock


def test_a_one_shot_run_ticks_to_success_paced_on_the_clock(tmp_path):
    record = tmp_path / "run.json"
    settings = {"decision_timeout": 5.0, "tick_period": 0.5, "progress_every": 1}
    loop, robots, clock = _loop([[0, 0]], [[0, 2]], settings, record_file=str(record))
    outcome = loop.run()
    assert outcome["success"] and outcome["steps"] == 2
    assert robots.states == [False, False, True]  # ticks 0 and 1, then the final state
    assert [p["tick"] for p in robots.progress] == [1, 2]
    assert robots.outcomes == [outcome]
    assert clock.slept == [0.5, 0.5]  # each tick paced to tick_period (the fake clock stood)
    assert ("info", outcome["summary"]) in robots.lines
    assert json.loads(record.read_text())["success"] is True


def test_a_missing_move_is_stay_and_settings_are_read_every_tick():
    settings = {"decision_timeout": 0.01, "tick_period": 0.0, "progress_every": 10}

    def change(tick):
        if tick == 0:  # a change during tick 0 (a runtime parameter) applies from tick 1
            settings["tick_period"] = 2.0

    loop, robots, clock = _loop([[0, 0], [0, 4]], [[0, 2], [0, 4]], settings, silent={1},
                                on_state=change, max_steps=3)
    outcome = loop.run()
    warnings = [text for level, text in robots.lines if level == "warning"]
    assert len(warnings) == 2 and all("1" in w for w in warnings)  # robot 1, ticks 0 and 1
    assert outcome["success"] and outcome["missed_decisions"] == 2
    assert clock.slept == [2.0]  # tick 0 unpaced, tick 1 paced after the change


def test_a_stop_ends_the_run_before_the_next_tick_with_its_outcome_and_record(tmp_path):
    record = tmp_path / "run.json"
    holder = {}

    def stop_at_tick_one(tick):
        if tick == 1:
            holder["ticker"].stop()

    loop, robots, clock = _loop([[0, 0]], [[0, 3]], {"decision_timeout": 5.0},
                                on_state=stop_at_tick_one, record_file=str(record))
    holder["ticker"] = loop.ticker
    outcome = loop.run()
    assert not outcome["success"] and "stopped at tick 1" in outcome["summary"]
    assert robots.states[-1] is True and len(robots.progress) == 1
    assert json.loads(record.read_text())["steps"] == 1
