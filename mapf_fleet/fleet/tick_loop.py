"""The lockstep tick loop of the simulator and the aggregator, without ROS (its specification).

`TickLoop(run, ticker, step, outlet, ...).run()` ticks `run` (a `fleet.run.FleetRun`) until it is
finished (every robot on its goal for a one-shot instance, the tick limit, every task done) or
stopped (`ticker.stop()`: a signal, a failed callback), and returns the outcome's fields.

Each tick k:
1. the state of k goes out once (`outlet.publish_state(done=False)`);
2. the robots' moves for k are collected (`ticker.collect(decision_timeout)`; a move missing
   after the timeout is "stay", logged as a warning); a stop here ends the run before k is
   played, so the record stays consistent;
3. under `lock`: `step(decisions) -> (events, overridden robot ids)` makes tick k + 1 (it calls
   `ticker.advance()` and `run.advance` / `run.step`), the run's progress is taken and the goal
   events go to `goals` (also the time the tick took, at least `tick_period`);
4. the events are logged (reached / assigned only for 16 robots or fewer), the progress is
   published and logged every `progress_every` ticks; at the first tick the record's head is
   written (marked incomplete; every tick goes to its journal as it ends, so a killed process
   leaves what it ran); the tick is paced to `tick_period`.
`decision_timeout`, `tick_period` and `progress_every` are read from `settings` every tick (the
node's runtime parameters). A continuous fleet with nothing to do (`run.waiting`: every robot
idle) does not tick: it republishes its state when it changes or every IDLE_STATE_PERIOD_S and
waits for a goal request (`goals.request_signal`).
At the end: the final state (`done=True`), the active tasks aborted with the reason, the goals
closed, the outcome (`run.finish`, `summary_extra()` appended; "stopped at tick k" after a stop)
published and the record written.

What it publishes is `FleetOutlet` (ROS: `ros.fleet_io.RosOutlet`; tests: `RecordingOutlet`);
the goal inputs are a `GoalIntake` (ROS: `ros.goals.GoalServer`). Time comes from `clock` and
`sleep`, so a test runs it on a fake clock.
"""

from __future__ import annotations

import time
from typing import Callable, Mapping, Protocol

IDLE_STATE_PERIOD_S = 1.0  # an idle fleet republishes its state this often


class FleetOutlet(Protocol):
    """What the tick loop publishes: the state of the current tick, a tick's progress
    (`FleetRun.progress`), the outcome (`FleetRun.finish`), and log lines."""

    def publish_state(self, done: bool) -> None: ...

    def publish_progress(self, progress: dict) -> None: ...

    def publish_outcome(self, outcome: dict) -> None: ...

    def log(self, level: str, text: str) -> None: ...  # level: info, warning, error


class GoalIntake(Protocol):
    """Goals given at run time (`ros.goals.GoalServer`): told each tick's events, woken by a
    request, closed at the end."""

    request_signal: object  # .wait(seconds)

    def on_tick(self, events, overridden=(), tick_seconds: float | None = None) -> None: ...

    def close(self, reason: str) -> None: ...


class RecordingOutlet:
    """A `FleetOutlet` that keeps what it is given (the in-memory double of the ROS topics)."""

    def __init__(self):
        self.states: list[bool] = []  # done flags, one per state published
        self.progress: list[dict] = []
        self.outcomes: list[dict] = []
        self.lines: list[tuple[str, str]] = []

    def publish_state(self, done: bool) -> None:
        self.states.append(bool(done))

    def publish_progress(self, progress: dict) -> None:
        self.progress.append(dict(progress))

    def publish_outcome(self, outcome: dict) -> None:
        self.outcomes.append(dict(outcome))

    def log(self, level: str, text: str) -> None:
        self.lines.append((level, text))


class TickLoop:
    def __init__(self, run, ticker, step: Callable, outlet: FleetOutlet, *, lock,
                 settings: Mapping, goals: GoalIntake | None = None, record_file: str = "",
                 summary_extra: Callable[[], str] = lambda: "",
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep,
                 keep_going: Callable[[], bool] = lambda: True):
        self.fleet_run, self.ticker, self.step, self.outlet = run, ticker, step, outlet
        self.lock, self.settings, self.goals = lock, settings, goals
        self.record_file, self.summary_extra = record_file, summary_extra
        self.clock, self.sleep, self.keep_going = clock, sleep, keep_going

    def _setting(self, name: str, default, kind):
        return kind(self.settings.get(name, default))

    def run(self) -> dict:
        """Tick until finished or stopped; the outcome's fields (FleetOutcome)."""
        run, ticker, outlet, goals = self.fleet_run, self.ticker, self.outlet, self.goals
        published, published_at = None, 0.0  # the tick whose state is out, and when
        checkpointed = False  # the record is written (incomplete) at the first tick only
        run.recorder.started = self.clock()  # run_seconds count from the first tick
        if self.record_file:  # every tick kept as it ends, whatever happens to this process
            # a tick leaves memory once in the journal: the record is streamed from it at the end
            run.recorder.open_journal(self.record_file, keep_ticks=False)
        while not run.finished() and self.keep_going() and not ticker.stopped:
            if run.waiting and goals is not None:
                if published != run.tick or self.clock() - published_at > IDLE_STATE_PERIOD_S:
                    # the robots decide this tick once; their moves wait in the ticker until a
                    # goal comes (the same tick again keeps the hubs' episode binding alive)
                    if published != run.tick:
                        outlet.log("info", f"tick {run.tick}: every robot idle: waiting for "
                                           f"goals")
                    outlet.publish_state(False)
                    published, published_at = run.tick, self.clock()
                goals.request_signal.wait(0.2)
                with self.lock:
                    goals.on_tick(run.apply_requests())
                continue
            started = self.clock()
            decision_timeout = self._setting("decision_timeout", 10.0, float)
            tick_period = self._setting("tick_period", 0.0, float)
            progress_every = self._setting("progress_every", 10, int)
            if published != run.tick:
                outlet.publish_state(False)
                published = run.tick
            decisions = ticker.collect(decision_timeout)
            if ticker.stopped:
                break  # this tick is not played: the record stays consistent
            if decisions.missing:
                outlet.log("warning", run.recorder.missing_text(decisions, decision_timeout))
            with self.lock:
                events, overridden = self.step(decisions)
                progress = run.progress(decisions.missing)
                if goals is not None:
                    # the estimated time counts a tick as long as it is paced (tick_period)
                    goals.on_tick(events, overridden, max(self.clock() - started, tick_period))
            for event in events:
                if event.event not in ("reached", "assigned") or run.num_robots <= 16:
                    outlet.log("info", event.text())
            outlet.publish_progress(progress)
            if run.steps % progress_every == 0:
                outlet.log("info", run.progress_text())
            # the record's head for a process that dies before the end, written once: the
            # journal holds every tick after it and `read_record` joins them
            if self.record_file and not checkpointed:
                run.recorder.checkpoint(self.record_file, run.tick)
                checkpointed = True
            if tick_period > 0:
                self.sleep(max(0.0, tick_period - (self.clock() - started)))
        return self._finish()

    def _finish(self) -> dict:
        run, goals = self.fleet_run, self.goals
        self.outlet.publish_state(True)
        stopped_at = run.tick if self.ticker.stopped and not run.finished() else None
        with self.lock:
            reason = (f"the run ended at tick {run.tick}" if stopped_at is None
                      else f"the run was stopped at tick {run.tick}")
            events = run.abort_active(reason) if run.tasks.continuous else []
            if goals is not None:
                goals.on_tick(events)
                goals.close(reason)
            outcome = run.finish(extra=self.summary_extra(), stopped_at=stopped_at)
        self.outlet.publish_outcome(outcome)
        self.outlet.log("info", outcome["summary"])
        if self.record_file:
            self.fleet_run.recorder.write(self.record_file)
            self.fleet_run.recorder.close_journal(self.record_file)
        return outcome
