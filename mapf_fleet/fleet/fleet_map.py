"""The fleet's map as its goal choices read it (numpy only): which cells a robot can reach, the
nearest idle robot's distance, a parking cell, a robot's cells left to drive.

Every distance is the map's shared `grid.heuristic.DistanceTable` under the run's guidance (the
one the conflict rule reads), taken as the table keeps its rows: no -1 copy per goal (a guided
copy is float64, a new goal's cost twice over on large maps; docs/results.md, "What guidance
costs"). `steps_to` is the one exception: cells left to drive are BFS steps whatever the
guidance (a guided distance is a cost, not a length)."""

from __future__ import annotations

import numpy as np

from mapf_fleet.grid.heuristic import distance_table


class FleetMap:
    """`grid` ((H, W), nonzero = obstacle) and its distances under `guidance` (None: BFS)."""

    def __init__(self, grid, guidance=None):
        self.grid = np.asarray(grid) != 0
        self.width = self.grid.shape[1]
        padded = np.pad(~self.grid, 1)
        self._free_neighbours = (padded[:-2, 1:-1].astype(int) + padded[2:, 1:-1]
                                 + padded[1:-1, :-2] + padded[1:-1, 2:])
        self.set_guidance(guidance)

    def set_guidance(self, guidance) -> None:
        """Every distance under `guidance` from now on (the run keeps which guidance it is)."""
        self.table = distance_table(self.grid, guidance)

    def _flat(self, cell) -> int:
        return int(cell[0]) * self.width + int(cell[1])

    def costs_to(self, cell) -> tuple[np.ndarray, float]:
        """(row, unreachable): the guided costs (or steps) to `cell`, flat, as the table keeps
        them, and the value at which a cell cannot reach it."""
        return self.table.whole(self._flat(cell)), self.table.unreachable

    def reaches(self, here, cell) -> bool:
        """Whether a robot at `here` can reach `cell`."""
        row, far = self.costs_to(cell)
        return bool(row[self._flat(here)] < far)

    def distance_to(self, cell) -> np.ndarray:
        """(H, W) distances to `cell` (-1 unreachable): BFS steps, or guided costs under the
        guidance (`DistanceTable.array`, a copy for callers that want -1)."""
        return self.table.array(self._flat(cell)).reshape(self.grid.shape)

    def steps_to(self, cell) -> np.ndarray:
        """(H, W) BFS steps to `cell` (-1 unreachable), whatever the guidance: what a robot has
        left to drive, in cells."""
        return distance_table(self.grid).array(self._flat(cell)).reshape(self.grid.shape)

    def nearest(self, robots, cells, cell) -> int | None:
        """The one of `robots` (ids) at `cells` ((N, 2)) nearest to `cell` under the guidance
        (ties: the first), None when none can reach it."""
        row, far = self.costs_to(cell)
        d = row[cells[:, 0] * self.width + cells[:, 1]]
        reachable = d < far
        if not reachable.any():
            return None
        return int(robots[np.flatnonzero(reachable)[np.argmin(d[reachable])]])

    def parking_cell(self, here, avoid) -> tuple[int, int] | None:
        """The nearest reachable free cell off `avoid`, at a junction (3+ free neighbours)
        where there is one: a corridor or dead-end cell would be on the busy robot's way in."""
        row, far = self.costs_to(here)
        dist = row.reshape(self.grid.shape)
        free = (dist > 0) & (dist < far)
        for cell in avoid:
            free[cell] = False
        if not free.any():
            return None
        if (free & (self._free_neighbours >= 3)).any():
            free &= self._free_neighbours >= 3
        flat = np.flatnonzero(free.ravel())
        best = flat[np.argmin(row[flat])]  # the nearest; ties: the first in row order
        return int(best // self.width), int(best % self.width)
