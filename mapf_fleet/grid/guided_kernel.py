"""Guided distances to a goal, compiled (numba): a goal's least path costs under a guidance graph
(`grid.guidance`) and its packed heuristic bits in one call, for many goals at once on the
machine's cores (docs/results.md, "What guidance costs").

Why not scipy's Dijkstra: its binary heap orders every cell by cost, which a BFS does not need,
and its row still needs numpy passes for the bits. Here the priority queue is a bucket queue
(Dial's, with float keys): bucket b holds the queued cells whose cost lies in [b D, (b + 1) D),
with D the least move cost of the graph. A cell of the lowest bucket cannot be improved by
another cell of that bucket (every move adds at least D), so the cells of a bucket are taken in
any order, as a BFS takes a level: no comparisons between costs. A bucket is taken in rounds:
its cells relax their neighbours without a branch (every improved neighbour goes on a list),
then the list is sorted into the buckets by the costs the round ended with.

Exact: the result is scipy's, bit for bit. Whatever order cells are taken in, a cell whose cost
drops is queued again (the search corrects its labels until nothing improves), so the costs are
the least, over every path, of the path's float64 sum added up from the goal: what every
Dijkstra computes (float addition is monotone), whichever ties it breaks. D only decides how
often a label is corrected: rounding at a bucket's edge may queue a cell in the bucket being
taken, and where the costs span more than `MAX_BUCKETS` least costs, D grows to keep the
circular array of buckets small and the cells of a bucket may correct each other
(Delta-stepping). A cell queued again leaves its old entry behind; an entry counts only where
the cell's cost still lies in the entry's bucket.

Layout: the map padded by one cell (no bounds checks); `incoming[v, k]` is the cost of the move
into v from its neighbour in direction k (0 up, 1 down, 2 left, 3 right), that is the
neighbour's move in the opposite direction (k ^ 1), inf where there is no such move (off the
map, from or into an obstacle, a forbidden one-way move): distances are TO the goal, so the
search runs from the goal over reversed moves (`Guidance.reverse_graph`'s orientation). Output
per goal, unpadded flat cells:
- row: float64 least path cost to the goal, inf on obstacles and where the goal is out of reach;
- bits: bit k where the move in direction k costs what it saves, `numpy.isclose`'s test exactly
  (the `heuristic._guided_bits` channels: the move lies on a least-cost path).
"""

from __future__ import annotations

import os
import threading

import numpy as np
from numba import njit

from .search_kernel import neighbour, on_threads

# the most buckets in the circular array; beyond it the bucket width grows (see above)
MAX_BUCKETS = 128
# numpy.isclose's default tolerances, which the guided bits use
RTOL, ATOL = 1e-5, 1e-8


@njit(cache=True, nogil=True)
def _row_and_bits(steps, dist, W, h, w, row, bits):  # pragma: no cover (compiled)
    """The row unpadded from `dist`, and the bits: numpy.isclose(step + there, here) where here
    is > 0 and finite. Written over one map row's slices at a time, which the compiler
    vectorises (element by element over the padded map it does not)."""
    for r in range(h):
        base = (r + 1) * W + 1
        here_ = dist[base:base + w]
        above, below = dist[base - W:base - W + w], dist[base + W:base + W + w]
        before, after = dist[base - 1:base - 1 + w], dist[base + 1:base + 1 + w]
        up, down = steps[0, base:base + w], steps[1, base:base + w]
        left, right = steps[2, base:base + w], steps[3, base:base + w]
        out_row, out_bits = row[r * w:(r + 1) * w], bits[r * w:(r + 1) * w]
        for c in range(w):
            here = here_[c]
            limit = ATOL + RTOL * here
            limit = limit if (here > 0.0) & (here < np.inf) else -1.0
            b = np.int32(abs(up[c] + above[c] - here) <= limit)
            b |= np.int32(abs(down[c] + below[c] - here) <= limit) << 1
            b |= np.int32(abs(left[c] + before[c] - here) <= limit) << 2
            b |= np.int32(abs(right[c] + after[c] - here) <= limit) << 3
            out_bits[c] = b
            out_row[c] = here


@njit(cache=True, nogil=True)
def _search(incoming, steps, W, h, w, goal, inv_width, mask, sizes, stacks, improved, dist,
            row, bits):  # pragma: no cover (compiled)
    """One goal's row and bits (module docstring) on the map padded by one cell (`W` = w + 2):
    `incoming` (padded cells, 4), `steps` (4, padded cells) the moves' costs, inf on the pad;
    `goal` a padded cell. Scratch: `sizes` (buckets), `stacks` (buckets, room), `improved`
    (4 room + 8), `dist` (padded cells), any contents; `row` and `bits` (unpadded) are written
    whole. Returns -1 where a bucket outgrew `stacks` (nothing written: search again with more
    room), else the number of cells taken from the queue."""
    dist[:] = np.inf
    sizes[:] = 0
    dist[goal] = 0.0
    stacks[0, 0] = goal
    sizes[0] = 1
    room = stacks.shape[1]
    queued = 1
    current = 0
    taken = 0
    while queued > 0:
        slot = current & mask
        i = 0
        while i < sizes[slot]:  # rounds: the bucket's cells, then the cells they queued in it
            end = sizes[slot]
            m = 0
            while i < end:
                v = stacks[slot, i]
                i += 1
                dv = dist[v]
                if np.int64(dv * inv_width) != current:  # left behind: queued lower since
                    continue
                taken += 1
                # branch-free relaxation: every improved neighbour goes on a list (`m` counts
                # the real ones), queued below from the cost it ends the round with
                for k in range(4):
                    u = neighbour(v, k, W)
                    du = dv + incoming[v, k]
                    old = dist[u]
                    dist[u] = min(du, old)
                    improved[m] = u
                    m += du < old
            for j in range(m):
                u = improved[j]
                to = np.int64(dist[u] * inv_width) & mask
                count = sizes[to]
                if count == room:
                    return -1
                stacks[to, count] = u
                sizes[to] = count + 1
            queued += m
        queued -= i
        sizes[slot] = 0
        current += 1
    _row_and_bits(steps, dist, W, h, w, row, bits)
    return taken


def incoming_costs(blocked: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(H + 2, W + 2, 4) on the map padded by one cell: the cost of the move into each cell from
    its neighbour in direction k (0 up, 1 down, 2 left, 3 right), the neighbour's step cost in
    the opposite direction (`steps`: (H*W, 5), `Guidance.step_costs()`); inf where there is no
    such move whatever `steps` holds (off the map, from or into an obstacle): the search never
    leaves the padded map."""
    h, w = blocked.shape
    free = np.zeros((h + 4, w + 4), dtype=bool)
    free[2:-2, 2:-2] = ~blocked
    pad = np.full((h + 4, w + 4, 5), np.inf)
    pad[2:-2, 2:-2] = steps.reshape(h, w, 5)
    into = np.full((h + 2, w + 2, 4), np.inf)
    here = free[1:-1, 1:-1]
    # from the neighbour above (direction 0) the move is down (action 2), and so on
    for k, (dr, dc, action) in enumerate(((-1, 0, 2), (1, 0, 1), (0, -1, 4), (0, 1, 3))):
        there = (slice(1 + dr, h + 3 + dr), slice(1 + dc, w + 3 + dc))
        into[..., k] = np.where(here & free[there], pad[there + (action,)], np.inf)
    return into


class GuidedSearcher:
    """Compiled guided search over one map (`blocked`, (H, W) bool) under step costs `steps`
    ((H*W, 5), `Guidance.step_costs()`: costs > 0, inf where a move is forbidden or impossible):
    `search(goals)` gives each flat goal cell's float64 row (inf where unreachable) and uint8
    bits; batches run on up to `threads` threads (the search releases the GIL)."""

    def __init__(self, blocked: np.ndarray, steps: np.ndarray, threads: int | None = None):
        self.blocked = np.asarray(blocked, dtype=bool)
        self.h, self.w = h, w = self.blocked.shape
        self.W = w + 2
        steps = np.asarray(steps, dtype=np.float64).reshape(-1, 5)
        if steps.shape[0] != self.blocked.size:
            raise ValueError(f"step costs are for {steps.shape[0]} cells, the map has "
                             f"{self.blocked.size}")
        into = incoming_costs(self.blocked, steps)
        self.incoming = np.ascontiguousarray(into.reshape(-1, 4))
        moves = self.incoming[np.isfinite(self.incoming)]
        if (moves <= 0).any() or np.isnan(moves).any():
            raise ValueError(f"move costs must be > 0, got {moves[~(moves > 0)][0]:g}")
        pad = np.full((h + 2, w + 2, 4), np.inf)
        pad[1:-1, 1:-1] = steps.reshape(h, w, 5)[..., 1:]
        self.steps = np.ascontiguousarray(np.moveaxis(pad, -1, 0).reshape(4, -1))
        least = float(moves.min()) if moves.size else 1.0
        most = float(moves.max()) if moves.size else 1.0
        # no path costs more than (free cells) x (dearest move): bucket numbers stay below 2^30,
        # where float rounding cannot move a cost by a whole bucket
        free = int((~self.blocked).sum())
        width = max(least, most / (MAX_BUCKETS - 4), free * most / 2.0 ** 30)
        self.inv_width = 1.0 / width if np.isfinite(width) else 0.0
        # a new cost lies at most floor(most / width) + 2 buckets past the bucket being taken:
        # the buckets in use never share a slot of the circular array
        span = int(most * self.inv_width) + 4
        self.buckets = 1 << max(2, (span - 1).bit_length())
        # a bucket's room: a wavefront's worth to start with, doubled whenever one outgrows it
        self.room = min(self.incoming.shape[0], 1024 + 8 * (h + w))
        self.threads = max(1, threads or len(os.sched_getaffinity(0)))
        self._spare: list[tuple] = []
        self._lock = threading.Lock()

    def _scratch(self) -> tuple:
        """A free set of the search's scratch arrays (kept between searches: fresh ones cost
        page faults on every search), or a new one."""
        with self._lock:
            if self._spare:
                return self._spare.pop()
        size, room = self.incoming.shape[0], self.room
        return (np.empty(self.buckets, np.int64), np.empty((self.buckets, room), np.int32),
                np.empty(4 * room + 8, np.int32), np.empty(size, np.float64))

    def _one(self, goals, rows, bits) -> None:
        sizes, stacks, improved, dist = self._scratch()
        for goal, row, out in zip(goals, rows, bits):
            r, c = divmod(goal, self.w)
            if self.blocked[r, c]:  # a goal on an obstacle: nothing reaches it
                row[:] = np.inf
                out[:] = 0
                continue
            # a round takes at most a bucket's room of cells: 4 improvements each at most
            while _search(self.incoming, self.steps, self.W, self.h, self.w,
                          (r + 1) * self.W + c + 1, self.inv_width, self.buckets - 1, sizes,
                          stacks, improved, dist, row, out) < 0:
                room = 2 * stacks.shape[1]
                self.room = max(self.room, room)
                stacks = np.empty((self.buckets, room), np.int32)
                improved = np.empty(4 * room + 8, np.int32)
        with self._lock:
            self._spare.append((sizes, stacks, improved, dist))

    def search(self, goals) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """(rows, bits): for each flat goal cell of `goals`, a new float64 (H*W,) row and a new
        uint8 (H*W,) bits array."""
        goals = [int(g) for g in goals]
        n = self.blocked.size
        rows = [np.empty(n, np.float64) for _ in goals]
        bits = [np.empty(n, np.uint8) for _ in goals]
        on_threads(lambda s: self._one(goals[s], rows[s], bits[s]), len(goals), self.threads)
        return rows, bits
