"""A goal's distances around one cell only: the first tick at scale (docs/results.md, "The first
tick at 10,000 agents").

`Windows` (a `DistanceTable`'s, unguided) keeps, per goal not searched whole yet, a window of
its distances and heuristic bits around the cell of the agent heading there, from a search
bounded to it (`search_kernel.Searcher.windows`: exact, as the whole search is there). The
observations gather from it (`grid.goal_observer.GoalObserver`) and the conflict rules read it
through `DistanceTable.row` (a `WindowRow`); the table forgets a goal's window when it searches
the goal whole.
"""

from __future__ import annotations

import threading
from typing import NamedTuple

import numpy as np


class Window(NamedTuple):
    """A goal's distances around one cell (`Windows.open`): the side x side cells
    from (row0, col0) (off the map included), flat: `static` the observation's bytes (obstacle
    bit, heuristic bits; `search_kernel.fill_static`'s), `dist` the distances (-1 where none),
    `values` the same with `row`'s convention (unreachable above any path)."""
    row0: int
    col0: int
    side: int
    static: np.ndarray
    dist: np.ndarray
    values: memoryview


class WindowRow:
    """`DistanceTable.row` of a goal searched only in a window so far: indexed by flat cell as
    the whole row is; a cell outside the window searches the goal whole first (the conflict
    rules read the cells around an agent, which its window holds). `numpy.asarray` gives the
    whole row."""

    __slots__ = ("table", "goal", "row0", "col0", "side", "values", "width")

    def __init__(self, table, goal: int, window: Window):
        self.table, self.goal = table, goal
        self.row0, self.col0, self.side, self.values = (window.row0, window.col0, window.side,
                                                        window.values)
        self.width = table.shape[1]

    def __getitem__(self, cell: int):
        r, c = divmod(cell, self.width)
        r, c = r - self.row0, c - self.col0
        if 0 <= r < self.side and 0 <= c < self.side:
            return self.values[r * self.side + c]
        return self.table.whole(self.goal)[cell]

    def __len__(self) -> int:
        return self.table.size

    def __array__(self, dtype=None, copy=None):
        row = self.table.whole(self.goal)  # read-only: `numpy.array` asks for a copy
        return row.astype(row.dtype if dtype is None else dtype) if copy or dtype is not None \
            else row


class Windows:
    """The windows of one map's goals (`Window`), searched by `searcher`
    (`search_kernel.Searcher`)."""

    def __init__(self, searcher):
        self.searcher = searcher
        self._windows: dict[int, Window] = {}
        self._lock = threading.Lock()  # fleet processes decide in threads
        self.cells = 0  # cells settled by the bounded searches so far

    def open(self, goals, centres, half: int, skip=()) -> None:
        """Search each flat goal cell of `goals` (not in `skip`: searched whole already) in
        the (2 half + 1)^2 cells around the cell (row, col) of `centres`."""
        goals = [int(g) for g in goals]
        keep = [k for k, g in enumerate(goals) if g not in skip]
        if not keep:
            return
        goals = [goals[k] for k in keep]
        centres = np.asarray(centres, dtype=np.int64).reshape(-1, 2)[keep]
        static, dist, settled = self.searcher.windows(goals, centres, half)
        side = 2 * int(half) + 1
        values = np.where(dist < 0, self.searcher.unreachable, dist)  # `row`'s convention
        with self._lock:
            self.cells += settled
            for k, (g, (r, c)) in enumerate(zip(goals, centres.tolist())):
                self._windows[g] = Window(r - half, c - half, side, static[k], dist[k],
                                          memoryview(values[k]))

    def get(self, goal: int) -> Window | None:
        """Flat cell `goal`'s window, None once it is searched whole (or never was windowed)."""
        return self._windows.get(int(goal))

    def close(self, goals) -> None:
        """Forget the windows of `goals` (searched whole, or nobody heads there any more)."""
        with self._lock:
            for g in goals:
                self._windows.pop(int(g), None)
