"""What a fleet run records (numpy only): counts, the per-tick trajectory, every goal change and
the outcome texts. `FleetRun` owns one; the simulator, the aggregator and the evaluator's
lifelong rollout all record through it, so their records have one format.

Record (JSON, `write`): `episode`, `task_source`, `conflict_rule`, `goals` (the first goals),
`positions` (T + 1 lists of N cells), `actions` (first choices per tick), `missed` (robots
without a decision per tick), the node's own `series` (e.g. "executed", "overridden",
"rejected"), `goal_events` (every goal change: assigned, reached, preempted, cancelled, aborted,
rejected, with tick, robot, cell, source and id), and at the end the outcome's figures.
`write` is atomic, and a node calls it every `checkpoint_every` ticks during the run, so a killed
process leaves the ticks it ran (issue 23: a dead simulator lost its whole trajectory).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class Decisions:
    """The moves collected for one tick; a missing robot's action is 0 (stay), its
    preferences [0, 1, 2, 3, 4]."""

    tick: int
    actions: np.ndarray            # (N,) int64: first choices
    preferences: np.ndarray        # (N, 5) int64: each robot's actions ranked, best first
    missing: list[int]             # robots without a move by the deadline
    requested: list[list[int]]     # per robot: DHC partners / DCC requested peers
    messages: list[int]            # per robot: peer messages it used

    @classmethod
    def complete(cls, tick: int, preferences) -> "Decisions":
        """Every robot decided (the evaluator's rollout): rankings (N, 5), no messages."""
        prefs = np.asarray(preferences, dtype=np.int64)
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
        """The record as JSON, atomically (a reader never sees half a file)."""
        from mapf_fleet.files import atomic_write

        atomic_write(path, json.dumps(self.record).encode())
