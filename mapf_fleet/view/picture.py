"""`FleetPicture`: what a viewer shows of a fleet, built from the fleet's messages (as plain
values, so the live view, the recorded-run renderer and the tests share it; no rclpy).

- the map (`set_map`: obstacle grid, 1 = obstacle, and its geometry);
- the robots' cells and their current goals (`set_state`, one call per FleetState: the goals come
  from the state itself, so goals given to robots during a run are drawn as they change);
- the paths taken: each robot's cells since the picture saw its episode start (the last `trail`
  cells; a new episode id starts them afresh);
- the tick, the robots on their goal, the goals reached and the throughput: goals reached per
  tick (also over the last `window` ticks), the figure that matters when the fleet runs
  continuously with new goals;
- the progress counters (`set_progress`) and the outcome (`set_outcome`).

Goals reached: the fleet's own count when its progress carries one (FleetProgress.goals_reached;
throughput = goals_reached / tick, as the fleet defines it, right even for a view started in the
middle of a run); else counted here from the states: a goal counts once per (robot, goal cell),
when the robot stands on its current goal or its goal changes while it stands on the old one
(the new goal was given in the tick it arrived), and the throughput runs from the first tick
this picture saw. A robot pushed off its goal and back does not count twice. Not counted: a
goal the robot already stands on when the picture first sees it, and a goal that becomes the
robot's own cell (an idle robot's goal is the cell it is in, updated every tick).

Thread safety: ROS callbacks write, the web server's threads read `snapshot()` / wait in
`wait_change`; one lock guards everything.
"""

from __future__ import annotations

import threading
from collections import deque

import numpy as np

# robot i's colour: one formula for the page (it gets the colours from `snapshot`), Foxglove and
# `mapf-fleet render` (evaluation.render, below this layer)
from mapf_fleet.evaluation.render import robot_colour  # noqa: F401


class FleetPicture:
    def __init__(self, trail: int = 500, window: int = 50):
        if trail < 1 or window < 1:
            raise ValueError(f"trail and window must be >= 1, got {trail} and {window}")
        self.trail = int(trail)
        self.window = int(window)
        self._cond = threading.Condition()
        self.version = 0  # bumped on every change
        self.map_version = 0
        self.grid: np.ndarray | None = None
        self.geometry = {"resolution": 1.0, "origin_x": 0.0, "origin_y": 0.0}
        self._reset_episode(None)

    # ---- writers --------------------------------------------------------------------------
    def _reset_episode(self, episode):
        self.episode = episode
        self.tick = None
        self.first_tick = None
        self.done = False
        self.positions = np.zeros((0, 2), np.int64)
        self.goals = np.zeros((0, 2), np.int64)
        self.trails: list[deque] = []
        self.reached_here = 0  # counted from the states
        self.reached_fleet = None  # FleetProgress.goals_reached, when the fleet reports it
        self.fleet_tick = None  # the tick of that progress
        self._counted: list[tuple[int, int] | None] = []
        # (tick, goals reached by then), one entry per tick, for the recent throughput
        self._history: deque = deque(maxlen=self.window + 1)
        self.progress: dict = {}
        self.outcome: dict = {}

    def _changed(self, map_too: bool = False):
        self.version += 1
        if map_too:
            self.map_version += 1
        self._cond.notify_all()

    def set_map(self, grid, resolution: float = 1.0, origin_x: float = 0.0,
                origin_y: float = 0.0) -> None:
        grid = (np.asarray(grid) != 0).astype(np.uint8)
        if grid.ndim != 2 or 0 in grid.shape:
            raise ValueError(f"map must be a non-empty 2-D grid, got shape {grid.shape}")
        with self._cond:
            self.grid = grid
            self.geometry = {"resolution": float(resolution), "origin_x": float(origin_x),
                             "origin_y": float(origin_y)}
            self._changed(map_too=True)

    def set_state(self, episode: int, tick: int, positions, goals, done: bool = False) -> None:
        positions = np.asarray(positions, dtype=np.int64).reshape(-1, 2)
        goals = np.asarray(goals, dtype=np.int64).reshape(-1, 2)
        if len(goals) != len(positions):
            raise ValueError(f"fleet state of tick {tick}: {len(positions)} robots but "
                             f"{len(goals)} goals")
        with self._cond:
            if episode != self.episode or len(positions) != len(self.positions):
                self._reset_episode(episode)
            elif self.tick is not None and tick < self.tick:
                return  # an older state arriving late: keep the newer one
            if self.first_tick is None:
                self.first_tick = int(tick)
                self.trails = [deque(maxlen=self.trail) for _ in range(len(positions))]
                self._counted = [None] * len(positions)
            first = len(self.goals) != len(goals)
            old_goals = goals if first else self.goals
            for i, (cell, goal, old) in enumerate(zip(positions.tolist(), goals.tolist(),
                                                      old_goals.tolist())):
                if not self.trails[i] or list(self.trails[i][-1]) != cell:
                    self.trails[i].append(tuple(cell))
                if old != goal and cell == old and self._counted[i] != tuple(old):
                    self._counted[i] = tuple(old)  # arrived as its next goal was given
                    self.reached_here += 1
                if cell == goal and (first or old != goal):
                    self._counted[i] = tuple(goal)  # already there, or idle: not a reach
                elif cell == goal and self._counted[i] != tuple(goal):
                    self._counted[i] = tuple(goal)
                    self.reached_here += 1
            self.tick = int(tick)
            self.done = bool(done)
            self.positions, self.goals = positions, goals
            if self.reached_fleet is None:
                self._note(self.tick, self.reached_here)
            self._changed()

    def _note(self, tick: int, reached: int) -> None:
        if self._history and self._history[-1][0] >= tick:
            self._history[-1] = (tick, reached)
        else:
            self._history.append((tick, reached))

    def set_progress(self, episode=None, **fields) -> None:
        """FleetProgress fields (tick, max_steps, on_goal, collisions, missed_decisions and,
        from fleets that count them, goals_reached)."""
        with self._cond:
            if episode is not None and self.episode is not None and episode != self.episode:
                return  # another run's: its states will reset the picture first
            self.progress = dict(fields)
            if fields.get("goals_reached") is not None and fields.get("tick") is not None:
                if self.reached_fleet is None:
                    self._history.clear()
                self.reached_fleet = int(fields["goals_reached"])
                self.fleet_tick = int(fields["tick"])
                self._note(self.fleet_tick, self.reached_fleet)
            self._changed()

    @property
    def reached(self) -> int:
        return self.reached_here if self.reached_fleet is None else self.reached_fleet

    def set_outcome(self, success: bool, summary: str, episode=None) -> None:
        with self._cond:
            if episode is not None and self.episode is not None and episode != self.episode:
                return  # the latched outcome of an earlier run
            self.outcome = {"success": bool(success), "summary": str(summary)}
            self._changed()

    # ---- readers --------------------------------------------------------------------------
    def wait_change(self, since: int, timeout: float) -> int:
        """Block until `version` differs from `since` (or `timeout` s); the current version."""
        with self._cond:
            self._cond.wait_for(lambda: self.version != since, timeout)
            return self.version

    def throughput(self) -> tuple[float, float]:
        """(goals reached per tick, the same over the last `window` ticks)."""
        with self._cond:
            if self.reached_fleet is not None:
                total = self.reached_fleet / self.fleet_tick if self.fleet_tick else 0.0
            elif self.tick is None or self.tick <= self.first_tick:
                total = 0.0
            else:
                total = self.reached_here / (self.tick - self.first_tick)
            recent = 0.0
            if len(self._history) >= 2:
                (t0, r0), (t1, r1) = self._history[0], self._history[-1]
                recent = (r1 - r0) / (t1 - t0) if t1 > t0 else 0.0
            return total, recent

    def map_snapshot(self) -> dict:
        """JSON-ready map: rows of '0'/'1' (1 = obstacle), row 0 first, and its geometry."""
        with self._cond:
            if self.grid is None:
                return {"type": "map", "height": 0, "width": 0, "rows": [], **self.geometry}
            rows = ["".join("1" if v else "0" for v in row) for row in self.grid.tolist()]
            return {"type": "map", "height": int(self.grid.shape[0]),
                    "width": int(self.grid.shape[1]), "rows": rows, **self.geometry}

    def snapshot(self) -> dict:
        """JSON-ready state: tick, robots, goals, paths taken, counts, throughput."""
        total, recent = self.throughput()
        with self._cond:
            on_goal = int((self.positions == self.goals).all(1).sum()) if len(self.goals) else 0
            return {
                "type": "state", "episode": None if self.episode is None else str(self.episode),
                "tick": self.tick, "first_tick": self.first_tick, "done": self.done,
                "robots": self.positions.tolist(), "goals": self.goals.tolist(),
                "colours": ["#%02x%02x%02x" % robot_colour(i) for i in range(len(self.goals))],
                "trails": [[list(c) for c in t] for t in self.trails],
                "on_goal": on_goal, "reached": self.reached,
                "throughput": round(total, 4), "throughput_window": round(recent, 4),
                "window": self.window, "window_ticks": (self._history[-1][0] - self._history[0][0]
                                                        if self._history else 0),
                "reached_by": "fleet" if self.reached_fleet is not None else "view", "progress": dict(self.progress),
                "outcome": dict(self.outcome), "has_map": self.grid is not None,
                "version": self.version,
            }
