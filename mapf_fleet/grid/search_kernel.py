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

Bounded searches (`Searcher.windows`): a goal's distances and bits in one window of the map
only (an agent's field of view and a margin), from an A* that stops once every cell of the
window and the ring around it is settled: exact, as the whole search is there. On a random
512x512 map a window 340 steps from its goal settles about a sixth of the map, and writes
nothing beyond the window (a whole search writes 0.8 MB a goal): the first tick at 10,000
agents searches windows, and the goals are searched whole over the next ticks
(`grid.goal_observer.GoalObserver`).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit

BLOCKED, UNSEEN = -2, -1


@njit(cache=True, nogil=True, inline="always")
def neighbour(v, k, W):  # pragma: no cover (compiled)
    """The padded flat cell next to `v` in direction k (0 up, 1 down, 2 left, 3 right) on a map
    padded to width `W`: every search's one step."""
    if k == 0:
        return v - W
    if k == 1:
        return v + W
    if k == 2:
        return v - 1
    return v + 1


def on_threads(run, count: int, threads: int) -> None:
    """`run(part)` for the stripes `part` = slice(k, None, workers) of `count` items, on up to
    `threads` threads at once (at least 8 items a thread): the searches release the GIL, so a
    batch of goals runs on every core."""
    workers = min(threads, max(1, count // 8))
    parts = [slice(k, None, workers) for k in range(workers)]
    if workers == 1:
        run(parts[0])
    else:
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(run, parts))


@njit(cache=True, nogil=True)
def _search(init, W, goal, scratch, queue, bits, row, out_bits, h, w, unreachable, static,
            pad):  # pragma: no cover (compiled)
    """One goal's BFS: its row, and its bits into `out_bits` (pad < 0) or, as `fill_static`
    writes them, into the padded map `static` (pad >= 0: no bits array to touch and copy)."""
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
            u = neighbour(v, k, W)
            du = scratch[u]
            new = du == UNSEEN
            queue[tail] = u  # harmless when not new: the next one overwrites it
            tail += new
            scratch[u] = dv if new else du
            # from u, v lies in the opposite direction (k ^ 1) and is one step closer
            bits[u] |= np.uint8((new | (du == dv)) << (k ^ 1))
    if pad < 0:
        for r in range(h):
            base = (r + 1) * W + 1
            for c in range(w):
                d = scratch[base + c]
                row[r * w + c] = d if d >= 0 else unreachable
                out_bits[r * w + c] = bits[base + c]
        return
    wp = w + 2 * pad
    static[:pad * wp] = 1  # off the map: obstacles
    static[(h + pad) * wp:] = 1
    for r in range(h):
        base = (r + 1) * W + 1
        at = (r + pad) * wp
        static[at:at + pad] = 1
        static[at + pad + w:at + wp] = 1
        at += pad
        for c in range(w):
            d = scratch[base + c]
            row[r * w + c] = d if d >= 0 else unreachable
            static[at + c] = np.uint8(d == BLOCKED) | (bits[base + c] << 1)


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
        self._comp = None  # the pieces of free cells (`_components`)
        self.threads = max(1, threads or len(os.sched_getaffinity(0)))
        if blocked.size + 1 <= INT16_MAX:
            self.dtype, self.unreachable = np.int16, blocked.size + 1
        elif _longest_path_bound(self, blocked) < INT16_MAX:
            self.dtype, self.unreachable = np.int16, INT16_MAX
        else:
            self.dtype, self.unreachable = np.int32, blocked.size + 1
        # the search's own scratch map in the same type: half the cache lines where int16
        self.init = self.init.astype(self.dtype)

    def _one(self, goals, rows, bits, unreachable: int, statics=None, pad: int = -1) -> None:
        size = self.init.size
        scratch = np.empty(size, self.init.dtype)
        queue = np.empty(size + 4, np.int32)
        padded_bits = np.empty(size, np.uint8)
        none = np.empty(0, np.uint8)
        for k, (goal, row) in enumerate(zip(goals, rows)):
            r, c = divmod(int(goal), self.w)
            _search(self.init, self.W, (r + 1) * self.W + c + 1, scratch, queue, padded_bits,
                    row, none if bits is None else bits[k], self.h, self.w, unreachable,
                    none if statics is None else statics[k], pad)

    def search(self, goals, statics=None, pad: int = 0) -> tuple[list[np.ndarray], list]:
        """(rows, bits): for each flat goal cell of `goals`, a new (H*W,) distance row (`dtype`)
        and a new uint8 (H*W,) bits array; with `statics` (one uint8 array of
        (H + 2 pad) * (W + 2 pad) per goal) the bits go there instead, as `fill_static` writes
        them, and bits is None."""
        goals = [int(g) for g in goals]
        n = self.h * self.w
        rows = [np.empty(n, self.dtype) for _ in goals]
        bits = None if statics is not None else [np.empty(n, np.uint8) for _ in goals]
        pad = -1 if statics is None else int(pad)

        def run(s):
            self._one(goals[s], rows[s], None if bits is None else bits[s], self.unreachable,
                      None if statics is None else statics[s], pad)

        on_threads(run, len(goals), self.threads)
        return rows, bits

    # ---- bounded searches: one goal's observation window ---------------------------------------
    def _window_scratch(self):
        size = self.init.size
        return (np.full(size, -1, np.int32), np.zeros(size, np.uint8),
                np.empty((3, 4 * size), np.int64), np.zeros(3, np.int64),
                np.empty(size, np.int32))

    def _components(self) -> np.ndarray:
        """(padded cells,) int32 the 4-connected piece of free cells each cell is in (0 for
        blocked ones), labelled on first use."""
        if self._comp is None:
            from scipy.ndimage import label

            blocked = (self.init == BLOCKED).reshape(self.h + 2, self.w + 2)
            self._comp = label(~blocked)[0].astype(np.int32).reshape(-1)
        return self._comp

    def windows(self, goals, centres, half: int) -> tuple[np.ndarray, np.ndarray, int]:
        """(static, distances, settled): for each flat goal cell of `goals` and unpadded cell
        (row, col) of `centres`, the S x S window (S = 2 half + 1) centred there, `fill_static`'s
        bytes (uint8 (N, S*S)) and the distances to the goal (int32 (N, S*S), -1 where none),
        from an A* bounded to the window (`_window`): the cells settled in all, beside a whole
        search's free cells per goal."""
        goals = [int(g) for g in goals]
        centres = np.asarray(centres, dtype=np.int64).reshape(-1, 2)
        side = 2 * int(half) + 1
        static = np.empty((len(goals), side * side), np.uint8)
        dist = np.empty((len(goals), side * side), np.int32)
        comp = self._components()
        blocked = (self.init == BLOCKED).reshape(self.h + 2, self.w + 2)[1:-1, 1:-1]
        blocked = np.ascontiguousarray(blocked).reshape(-1).view(np.uint8)
        box = (side + 2) ** 2
        settled = np.zeros(len(goals), np.int64)

        def run(part):
            g, closed, stacks, sizes, touched = self._window_scratch()
            out = np.empty(box, np.int32)
            for k in range(part.start, len(goals), part.step):
                r, c = divmod(goals[k], self.w)
                settled[k] = _window(self.init, comp, blocked, self.W, self.h, self.w,
                                     (r + 1) * self.W + c + 1, int(centres[k, 0]),
                                     int(centres[k, 1]), int(half), g, closed, stacks, sizes,
                                     touched, out, static[k], dist[k],
                                     self.unreachable)

        on_threads(run, len(goals), self.threads)
        return static, dist, int(settled.sum())


def _longest_path_bound(searcher: Searcher, blocked: np.ndarray) -> int:
    """An upper bound on every shortest path of the map: twice the eccentricity of one cell of
    the largest connected piece (triangle inequality), and below the size of any other piece."""
    h, w = blocked.shape
    pieces = searcher._components().reshape(h + 2, w + 2)[1:-1, 1:-1]
    count = int(pieces.max())
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
    (`grid.goal_observer.GoalObserver`'s pool slot)."""
    wp = w + 2 * pad
    out[:] = 1
    for r in range(h):
        base = (r + pad) * wp + pad
        for c in range(w):
            out[base + c] = blocked[r * w + c] | (bits[r * w + c] << 1)


@njit(cache=True, nogil=True, inline="always")
def _to_box(vr, vc, r0, c0, r1, c1):  # pragma: no cover (compiled)
    """Steps from (vr, vc) to the box rows r0..r1, cols c0..c1 with no obstacle in the way: the
    search's heuristic (it changes by at most 1 a move: consistent)."""
    return max(r0 - vr, 0, vr - r1) + max(c0 - vc, 0, vc - c1)


@njit(cache=True, nogil=True)
def _bounded(init, comp, W, goal, r0, c0, rows, cols, g, closed, stacks, sizes,
             touched, out_dist, unreachable):  # pragma: no cover (compiled)
    """A* from `goal` (padded flat cell) over the padded map until every free cell of the box
    (padded rows r0.., cols c0.., `rows` x `cols`) that the goal reaches is settled; writes the
    box's distances into `out_dist` (rows*cols, `unreachable` where none). Scratch: `g` (-1
    everywhere) and `closed` (0 everywhere), the padded map's size, left as they were found.

    The heuristic (`_to_box`) is consistent, so a cell's distance is exact when it is taken from
    the queue; f grows by 0, 1 or 2 a move, so three LIFO stacks keyed by
    f modulo 3 are the priority queue (copies left behind by a shorter path are skipped).
    An entry packs the cell, its row and column. Returns the number of cells settled."""
    r1, c1 = r0 + rows - 1, c0 + cols - 1
    label = comp[goal]
    need = 0
    for i in range(rows):
        for j in range(cols):
            cell = (r0 + i) * W + c0 + j
            if label > 0 and comp[cell] == label:
                need += 1
    for b in range(3):
        sizes[b] = 0
    gr, gc = goal // W, goal % W
    f = _to_box(gr, gc, r0, c0, r1, c1)
    ntouched = 0
    if need > 0:
        g[goal] = 0
        touched[0] = goal
        ntouched = 1
        stacks[f % 3, 0] = goal | (gr << 32) | (gc << 48)
        sizes[f % 3] = 1
    settled = 0
    empty = 0
    while need > 0:
        b = f % 3
        if sizes[b] == 0:
            empty += 1
            if empty == 3:
                break
            f += 1
            continue
        empty = 0
        sizes[b] -= 1
        entry = stacks[b, sizes[b]]
        v = entry & 0xFFFFFFFF
        if closed[v]:
            continue
        vr, vc = (entry >> 32) & 0xFFFF, entry >> 48
        gv = g[v]
        hv = _to_box(vr, vc, r0, c0, r1, c1)
        if gv + hv != f:
            continue  # a copy from before a shorter path to the cell was found
        closed[v] = 1
        settled += 1
        if r0 <= vr <= r1 and c0 <= vc <= c1:
            need -= 1
        for k in range(4):
            u = neighbour(v, k, W)
            ur, uc = vr + (k == 1) - (k == 0), vc + (k == 3) - (k == 2)
            if init[u] == BLOCKED:
                continue
            gu = g[u]
            if gu >= 0 and gu <= gv + 1:
                continue
            if gu < 0:
                touched[ntouched] = u
                ntouched += 1
            g[u] = gv + 1
            bu = (gv + 1 + _to_box(ur, uc, r0, c0, r1, c1)) % 3
            stacks[bu, sizes[bu]] = u | (ur << 32) | (uc << 48)
            sizes[bu] += 1
    for i in range(rows):
        for j in range(cols):
            cell = (r0 + i) * W + c0 + j
            out_dist[i * cols + j] = g[cell] if closed[cell] else unreachable
    for t in range(ntouched):
        g[touched[t]] = -1
        closed[touched[t]] = 0
    return settled


@njit(cache=True, nogil=True)
def _window(init, comp, blocked, W, h, w, goal, cr, cc, half, g, closed, stacks, sizes,
            touched, box, out_static, out_dist, unreachable):  # pragma: no cover (compiled)
    """One goal's observation window: the S x S cells (S = 2 half + 1) centred on unpadded cell
    (cr, cc), as `fill_static` writes the padded map (bit 0 obstacle, off the map included; bits
    1-4 the heuristic bits) into `out_static`, and the distances (-1 where none) into
    `out_dist`. The search settles the window and one ring around it (a cell's bits compare it
    with its neighbours). Returns the number of cells settled."""
    top, left = max(cr - half - 1, 0), max(cc - half - 1, 0)
    bottom, right = min(cr + half + 1, h - 1), min(cc + half + 1, w - 1)
    rows, cols = bottom - top + 1, right - left + 1
    settled = _bounded(init, comp, W, goal, top + 1, left + 1, rows, cols, g, closed,
                       stacks, sizes, touched, box, unreachable)
    side = 2 * half + 1
    for i in range(side):
        r = cr - half + i
        for j in range(side):
            c = cc - half + j
            k = i * side + j
            if r < 0 or r >= h or c < 0 or c >= w:
                out_static[k] = 1
                out_dist[k] = -1
                continue
            at = (r - top) * cols + (c - left)
            d = box[at]
            bits = 0
            if d != unreachable:
                if r - 1 >= top and box[at - cols] == d - 1:
                    bits |= 1
                if r + 1 <= bottom and box[at + cols] == d - 1:
                    bits |= 2
                if c - 1 >= left and box[at - 1] == d - 1:
                    bits |= 4
                if c + 1 <= right and box[at + 1] == d - 1:
                    bits |= 8
            out_static[k] = blocked[r * w + c] | (bits << 1)
            out_dist[k] = d if d != unreachable else -1
    return settled
