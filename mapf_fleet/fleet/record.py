"""What a fleet run records (numpy only): counts, the per-tick trajectory, every goal change and
the outcome texts. `FleetRun` owns one; the simulator, the aggregator and the evaluator's
lifelong rollout all record through it, so their records have one format.

Record (JSON, `write`): `episode`, `task_source`, `conflict_rule`, `goals` (the first goals),
`positions` (T + 1 lists of N cells), `actions` (first choices per tick), `missed` (robots
without a decision per tick), the node's own `series` (e.g. "executed", "overridden",
"rejected"), `goal_events` (every goal change: assigned, reached, preempted, cancelled, aborted,
rejected, with tick, robot, cell, source and id), and at the end the outcome's figures.
`write` is atomic. A node also keeps a journal beside the record (`open_journal`: F.ticks, one
JSON line per tick, flushed as the tick ends) and removes it after the final `write`, so a
killed process leaves every tick it ran: `read_record` rebuilds the record from the journal
when the record is missing or incomplete.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Decisions:
    """The moves collected for one tick; a missing robot's action is 0 (stay), its
    rankings [0, 1, 2, 3, 4]."""

    tick: int
    actions: np.ndarray            # (N,) int64: first choices
    rankings: np.ndarray        # (N, 5) int64: each robot's actions ranked, best first
    missing: list[int]             # robots without a move by the deadline
    requested: list[list[int]]     # per robot: DHC partners / DCC requested peers
    messages: list[int]            # per robot: peer messages it used

    @classmethod
    def complete(cls, tick: int, rankings) -> "Decisions":
        """Every robot decided (the evaluator's rollout): rankings (N, 5), no messages."""
        prefs = np.asarray(rankings, dtype=np.int64)
        n = len(prefs)
        return cls(int(tick), prefs[:, 0].copy(), prefs, [], [[] for _ in range(n)], [0] * n)


@dataclass(frozen=True)
class GoalEvent:
    """One goal change. event: assigned | reached | preempted | cancelled | aborted |
    rejected | queued; robot -1: not (yet) a robot's (a queued or rejected "any robot" task);
    cell None: no cell (a rejected request whose cell could not be read)."""

    tick: int
    robot: int
    event: str
    cell: tuple | None
    source: str
    goal_id: str = ""
    reason: str = ""

    def to_dict(self) -> dict:
        out = asdict(self)
        out["cell"] = None if self.cell is None else [int(v) for v in self.cell]
        return out

    def text(self) -> str:
        who = f"robot {self.robot}" if self.robot >= 0 else "fleet"
        where = "" if self.cell is None else f" {tuple(int(v) for v in self.cell)}"
        why = f": {self.reason}" if self.reason else ""
        ident = f" [{self.goal_id}]" if self.goal_id else ""
        return f"tick {self.tick}: {who}: goal{where} {self.event} ({self.source}){ident}{why}"


class RunRecorder:
    """Counts, per-tick record and texts of one run. `series` names the node's own per-tick
    record entries (e.g. "collided", "rejected"), given to `add_tick` as keyword arguments."""

    def __init__(self, episode: int, num_robots: int, max_steps: int,
                 series=("requested", "messages"), conflict_rule: str = "",
                 task_source: str = "instance"):
        self.episode = int(episode)
        self.conflict_rule = conflict_rule
        self.task_source = task_source
        self.overridden = 0  # robots whose executed move was not their first choice
        self.num_robots = int(num_robots)
        self.max_steps = int(max_steps)  # 0: no limit (a continuous run until stopped)
        self.series = tuple(series)
        self.steps = self.collisions = self.missed = 0
        self.missed_robots: set[int] = set()
        self.record: dict = {"episode": self.episode, "task_source": task_source,
                             "positions": [], "actions": [], "missed": [], "goal_events": [],
                             **{name: [] for name in self.series}}
        if conflict_rule:
            self.record["conflict_rule"] = conflict_rule
        self.started = time.monotonic()
        self._journal = None  # open file of the per-tick journal (open_journal)
        self._journal_file = ""
        self.keep_ticks = True  # per-tick entries kept in memory (open_journal)
        self._journaled_events = 0

    def start(self, positions, goals) -> None:
        self.record["positions"].append(np.asarray(positions).tolist())
        self.record["goals"] = np.asarray(goals).tolist()
        self.started = time.monotonic()

    def add_events(self, events) -> None:
        self.record["goal_events"].extend(e.to_dict() for e in events)

    def missing_text(self, decisions: Decisions, timeout: float) -> str:
        return (f"tick {decisions.tick}: no decision from robots {decisions.missing} within "
                f"{timeout} s: they stay")

    def add_tick(self, decisions: Decisions, positions, collisions: int, **series) -> None:
        """Count and record one tick."""
        if set(series) != set(self.series):
            raise ValueError(f"add_tick: expected series {sorted(self.series)}, "
                             f"got {sorted(series)}")
        self.steps += 1
        self.collisions += int(collisions)
        self.missed += len(decisions.missing)
        self.missed_robots.update(decisions.missing)
        self.record["actions"].append(np.asarray(decisions.actions).tolist())
        self.record["missed"].append(list(decisions.missing))
        for name, value in series.items():
            self.record[name].append(value)
        self.overridden += len(series.get("overridden", ()))
        self.record["positions"].append(np.asarray(positions).tolist())
        self._tick_series = tuple(series)
        self._tick_after = int(decisions.tick) + 1

    # ---- the per-tick journal ----
    def open_journal(self, record_path, keep_ticks: bool = True) -> None:
        """Start the journal of `record_path` (`journal_path`): the record so far, then one line
        per tick from here on, each flushed as its tick ends. `keep_ticks` False: a tick's
        entries leave memory once journaled and `write` streams them from the journal, so a
        fleet that runs for days holds no history (a record kept in memory grows with every
        tick: docs/results.md, "The ROS fleet at 128 / 256 / 512 / 1,024 robots")."""
        path = journal_path(record_path)
        self._journal = open(path, "w", encoding="utf-8")
        self._journal_file = path
        self.keep_ticks = keep_ticks
        header = {k: v for k, v in self.record.items()}
        self._journaled_events = len(self.record["goal_events"])
        self._journal.write(json.dumps({"record": header}) + "\n")
        self._journal.flush()

    def end_tick(self) -> None:
        """The tick recorded last is complete (its goal events too): into the journal."""
        if self._journal is None:
            return
        series = getattr(self, "_tick_series", ())
        events = self.record["goal_events"][self._journaled_events:]
        self._journaled_events = len(self.record["goal_events"])
        line = {"t": round(time.monotonic() - self.started, 4), "steps": self.steps,
                "tick": getattr(self, "_tick_after", self.steps),
                "collisions": self.collisions, "missed_decisions": self.missed,
                "actions": self.record["actions"][-1], "missed": self.record["missed"][-1],
                "positions": self.record["positions"][-1], "goal_events": events,
                "series": {name: self.record[name][-1] for name in series}}
        self._journal.write(json.dumps(line) + "\n")
        self._journal.flush()
        if not self.keep_ticks:
            for name in self.tick_keys:
                self.record[name] = []
            self._journaled_events = 0

    @property
    def tick_keys(self) -> tuple:
        """The record's per-tick entries (lists growing with the run)."""
        return ("positions", "actions", "missed", "goal_events", *self.series)

    def close_journal(self, record_path=None) -> None:
        """Stop journaling; with `record_path` (its record written whole), remove the journal."""
        if self._journal is not None:
            self._journal.close()
            self._journal = None
        if record_path is not None:
            try:
                os.remove(journal_path(record_path))
            except FileNotFoundError:
                pass

    def checkpoint(self, path, tick: int) -> None:
        """The record so far, marked incomplete (`finish` replaces these fields): what a reader
        finds if the process dies before the end."""
        if "summary" not in self.record or self.record.get("incomplete"):
            self.record.update(incomplete=True, success=False, steps=self.steps,
                               collisions=self.collisions, missed_decisions=self.missed,
                               run_seconds=time.monotonic() - self.started,
                               summary=f"incomplete: the run's record stops at tick {tick} "
                                       f"({self.steps} steps recorded; the process ended before "
                                       f"its outcome)")
        self.write(path)

    def write(self, path) -> None:
        """The record as JSON, atomically (a reader never sees half a file); with the ticks kept
        only in the journal (`open_journal(keep_ticks=False)`), each per-tick entry streamed
        from it, one line at a time."""
        from mapf_fleet.files import atomic_write

        if self._journal is None or self.keep_ticks:
            atomic_write(path, json.dumps(self.record).encode())
            return
        self._journal.flush()
        atomic_write(path, self._stream_record)

    def _stream_record(self, handle) -> None:
        keys = self.tick_keys
        with open(self._journal_file, encoding="utf-8") as journal:
            header = json.loads(journal.readline())["record"]
        fields = {k: v for k, v in {**header, **self.record}.items() if k not in keys}
        handle.write(("{" + ", ".join(f"{json.dumps(k)}: {json.dumps(v)}"
                                      for k, v in fields.items())).encode())
        for key in keys:
            handle.write(f", {json.dumps(key)}: [".encode())  # after "episode" and the rest
            first = True

            def put(item):
                nonlocal first
                handle.write(((", " if not first else "") + json.dumps(item)).encode())
                first = False

            for item in header.get(key, []):
                put(item)
            with open(self._journal_file, encoding="utf-8") as journal:
                journal.readline()
                for text in journal:
                    tick = json.loads(text)
                    if key == "goal_events":
                        for event in tick["goal_events"]:
                            put(event)
                    else:
                        put(tick["series"][key] if key in self.series else tick[key])
            for item in self.record.get(key, []):  # recorded after the last journaled tick
                put(item)
            handle.write(b"]")
        handle.write(b"}")


def journal_path(record_path) -> str:
    return f"{record_path}.ticks"


def read_record(path) -> dict:
    """A run record as written by `RunRecorder.write`, completed from its journal when the
    process died before the end (the record missing or incomplete, the journal longer): every
    tick the journal holds, `steps` and `run_seconds` from its last line, marked incomplete.
    FileNotFoundError when neither exists; ValueError for a record that is not JSON."""
    path = Path(path)
    record = None
    if path.exists():
        record = json.loads(path.read_text())
    journal = Path(journal_path(path))
    if not journal.exists() or (record is not None and not record.get("incomplete")):
        if record is None:
            raise FileNotFoundError(f"{path}: no such file")
        return record
    lines = journal.read_text(encoding="utf-8").splitlines()
    try:
        header = json.loads(lines[0])["record"]
    except (IndexError, ValueError, KeyError, TypeError):
        if record is None:
            raise ValueError(f"{journal}: not a run journal") from None
        return record
    ticks = []
    for text in lines[1:]:
        try:
            ticks.append(json.loads(text))
        except ValueError:
            break  # the line being written when the process died
    if record is not None and len(record.get("actions") or []) >= len(ticks):
        return record  # it holds every tick the journal has (a streamed record holds none)
    out = dict(header)
    series = [k for k in ticks[0]["series"]] if ticks else []
    for name in ("positions", "actions", "missed", "goal_events", *series):
        out[name] = list(out.get(name, []))
    for tick in ticks:
        out["actions"].append(tick["actions"])
        out["missed"].append(tick["missed"])
        out["positions"].append(tick["positions"])
        out["goal_events"].extend(tick["goal_events"])
        for name in series:
            out[name].append(tick["series"][name])
    last = ticks[-1] if ticks else {"t": 0.0, "steps": 0, "collisions": 0,
                                    "missed_decisions": 0}
    out.update(incomplete=True, success=False, steps=int(last["steps"]),
               collisions=int(last["collisions"]), missed_decisions=int(last["missed_decisions"]),
               run_seconds=float(last["t"]),
               summary=f"incomplete: the run's record stops at tick "
                       f"{int(last.get('tick', last['steps']))} ({int(last['steps'])} steps "
                       f"recorded; the process ended before its outcome; rebuilt from "
                       f"{journal.name})")
    return out


def complete_record(path) -> dict:
    """`read_record`, and when it was rebuilt from the journal, the rebuilt record written in
    place of the record (atomically) and the journal removed: the file alone then holds every
    tick the run ran."""
    from mapf_fleet.files import atomic_write

    record = read_record(path)
    journal = Path(journal_path(path))
    if journal.exists() and record.get("incomplete"):
        atomic_write(path, json.dumps(record).encode())
        journal.unlink()
    return record
