"""The breadth-first search to a goal, compiled (numba): a goal's distance row and its packed
heuristic bits in one pass, for many goals at once on the machine's cores.

Why compiled: a fleet's first tick searches every robot's goal (10,000 goals on a 512x512 map),
and the search is a queue loop over cells whose branches depend on the map; numpy cannot
vectorise it, and scipy's compiled BFS (`breadth_first_order`) returns a visiting order that
still has to be cut into levels and turned into bits with numpy passes over the whole map.
Here one loop writes both, and the loop itself is branch-free where the map decides
(docs/results.md, "The first tick at 10,000 agents").

The search runs on the map padded by one blocked cell on each side (no bounds checks):
`-2` marks blocked cells, `-1` free cells not reached yet. Output, per goal, unpadded flat cells:
- row: steps to the goal, `unreachable` (a value above any path) where the goal cannot be
  reached and on obstacles;
- bits: bit k (0 up, 1 down, 2 left, 3 right) where the neighbour in direction k is a free cell
  exactly one step closer to the goal (`heuristic` module's channels).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit

BLOCKED, UNSEEN = -2, -1


@njit(cache=True, nogil=True)
def _search(init, W, goal, scratch, queue, bits, row, out_bits, h, w, unreachable):  # pragma: no cover (compiled)
    scratch[:] = init
    bits[:] = 0
    tail = 0
    if scratch[goal] == UNSEEN:
        scratch[goal] = 0
        queue[0] = goal
        tail = 1
    head = 0
    while head < tail:
        v = queue[head]
        head += 1
        dv = scratch[v] + 1
        for k in range(4):
            if k == 0:
                u = v - W
            elif k == 1:
                u = v + W
            elif k == 2:
                u = v - 1
            else:
                u = v + 1
            du = scratch[u]
            new = du == UNSEEN
            queue[tail] = u  # harmless when not new: the next one overwrites it
            tail += new
            scratch[u] = dv if new else du
            # from u, v lies in the opposite direction (k ^ 1) and is one step closer
            bits[u] |= np.uint8((new | (du == dv)) << (k ^ 1))
    for r in range(h):
        base = (r + 1) * W + 1
        for c in range(w):
            d = scratch[base + c]
            row[r * w + c] = d if d >= 0 else unreachable
            out_bits[r * w + c] = bits[base + c]


INT16_MAX = int(np.iinfo(np.int16).max)


class Searcher:
    """Compiled BFS over one map (`blocked`, (H, W) bool): `search(goals)` gives each flat goal
    cell's distance row and uint8 bits; batches run on up to `threads` threads (the search
    releases the GIL).

    Rows are int16 whenever no path on the map can reach 32,767 steps (every map of up to
    32,766 cells; larger ones by a bound from one search, below), int32 otherwise: at 10,000
    goals on a 512x512 map the rows are the fleet's largest memory, and the first tick's time
    is spent largely in touching fresh pages. `unreachable` (above any path) marks obstacles
    and cells cut off from the goal: the map's cell count + 1 where that fits the type, else
    32,767."""

    def __init__(self, blocked: np.ndarray, threads: int | None = None):
        h, w = blocked.shape
        self.h, self.w, self.W = h, w, w + 2
        padded = np.ones((h + 2, w + 2), dtype=bool)
        padded[1:-1, 1:-1] = blocked
        self.init = np.where(padded, BLOCKED, UNSEEN).astype(np.int32).reshape(-1)
        self.threads = max(1, threads or len(os.sched_getaffinity(0)))
        if blocked.size + 1 <= INT16_MAX:
            self.dtype, self.unreachable = np.int16, blocked.size + 1
        elif _longest_path_bound(self, blocked) < INT16_MAX:
            self.dtype, self.unreachable = np.int16, INT16_MAX
        else:
            self.dtype, self.unreachable = np.int32, blocked.size + 1
        # the search's own scratch map in the same type: half the cache lines where int16
        self.init = self.init.astype(self.dtype)

    def _one(self, goals, rows, bits, unreachable: int) -> None:
        size = self.init.size
        scratch = np.empty(size, self.init.dtype)
        queue = np.empty(size + 4, np.int32)
        padded_bits = np.empty(size, np.uint8)
        for goal, row, out in zip(goals, rows, bits):
            r, c = divmod(int(goal), self.w)
            _search(self.init, self.W, (r + 1) * self.W + c + 1, scratch, queue, padded_bits,
                    row, out, self.h, self.w, unreachable)

    def search(self, goals) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """(rows, bits): for each flat goal cell of `goals`, a new (H*W,) distance row (`dtype`)
        and a new uint8 (H*W,) bits array."""
        goals = [int(g) for g in goals]
        n = self.h * self.w
        rows = [np.empty(n, self.dtype) for _ in goals]
        bits = [np.empty(n, np.uint8) for _ in goals]
        workers = min(self.threads, max(1, len(goals) // 8))
        if workers == 1:
            self._one(goals, rows, bits, self.unreachable)
        else:
            parts = [slice(k, None, workers) for k in range(workers)]
            with ThreadPoolExecutor(workers) as pool:
                list(pool.map(lambda s: self._one(goals[s], rows[s], bits[s], self.unreachable),
                              parts))
        return rows, bits


def _longest_path_bound(searcher: Searcher, blocked: np.ndarray) -> int:
    """An upper bound on every shortest path of the map: twice the eccentricity of one cell of
    the largest connected piece (triangle inequality), and below the size of any other piece."""
    from scipy.ndimage import label  # 4-connected pieces of free cells

    pieces, count = label(~blocked)
    if count == 0:
        return 0
    sizes = np.bincount(pieces.reshape(-1))[1:]
    order = np.argsort(sizes)[::-1]
    cell = int(np.flatnonzero(pieces.reshape(-1) == order[0] + 1)[0])
    row = np.empty(blocked.size, np.int32)
    bits = np.empty(blocked.size, np.uint8)
    searcher._one([cell], [row], [bits], -1)
    other = int(sizes[order[1]]) - 1 if count > 1 else 0
    return max(2 * int(row.max()), other)


@njit(cache=True, nogil=True)
def fill_static(blocked, bits, out, h, w, pad):  # pragma: no cover (compiled)
    """Write a goal's padded static FOV map into `out` ((h + 2 pad) * (w + 2 pad) uint8): bit 0
    the obstacle (every off-map cell is one), bits 1-4 the heuristic bits
    (`grid.observation.GoalObserver`'s pool slot)."""
    wp = w + 2 * pad
    out[:] = 1
    for r in range(h):
        base = (r + pad) * wp + pad
        for c in range(w):
            out[base + c] = blocked[r * w + c] | (bits[r * w + c] << 1)
