"""Distances to a goal over static obstacles (`DistanceTable`, one per map and guidance graph) and
the four heuristic observation channels.

Distances come from a compiled breadth-first search over the 4-connected free cells
(`search_kernel`, numba) that writes a goal's distance row and its heuristic bits in one pass,
a batch of goals on every core: a fleet's first tick searches every robot's goal at once
(docs/results.md, "The first tick at 10,000 agents"); a pure-Python BFS is what made the
reference environments reset slowly.

Conventions:
- `bfs_distances` returns int32 steps to the goal; obstacle cells and free cells that cannot reach
  the goal hold `UNREACHABLE` (-1).
- Heuristic channel k (0 up, 1 down, 2 left, 3 right) is 1 at a cell when its neighbour in
  direction k is a free cell exactly one step closer to the goal (that is what "strictly closer"
  means with BFS distances). Obstacles, unreachable cells and the goal itself have no bit set.
- Under a guidance graph (`grid.guidance`) distances are least path costs (float64, Dijkstra) and
  channel k marks a move on a least-cost path; unit costs give the BFS tables exactly.
- Internally the four channels are packed into one uint8 per cell (bit k = channel k): the
  environment gathers one byte per FOV cell instead of four, and the cache stays small.
"""

from __future__ import annotations

import threading
from array import array
from collections import OrderedDict

import numpy as np

from .actions import move_targets
from .guided_kernel import GuidedSearcher
from .search_kernel import Searcher, fill_static
from .windows import Windows, WindowRow

UNREACHABLE = -1
NUM_HEURISTIC_CHANNELS = 4
_BIT_WEIGHTS = np.array([1, 2, 4, 8], dtype=np.uint8)


def _as_grid(grid) -> np.ndarray:
    grid = np.asarray(grid)
    if grid.ndim != 2 or grid.shape[0] == 0 or grid.shape[1] == 0:
        raise ValueError(f"grid must be a non-empty 2-D array, got shape {grid.shape}")
    return grid != 0


def _as_goals(goals, shape) -> np.ndarray:
    goals = np.asarray(goals, dtype=np.int64).reshape(-1, 2)
    h, w = shape
    bad = (goals[:, 0] < 0) | (goals[:, 0] >= h) | (goals[:, 1] < 0) | (goals[:, 1] >= w)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"goal {tuple(goals[i].tolist())} is outside the {h}x{w} map")
    return goals


class DistanceTable:
    """Distances to goal cells on one map under one guidance graph: the one table every consumer
    of "distance to the goal" reads (the PIBT rules, LaCAM and the plan keeper, the fleet core,
    the observations' heuristic channels, the lifelong evaluator).

    Get the shared table of a map with `distance_table(grid, guidance)`: callers that search one
    goal at a time (the conflict rules, a fleet's goal checks, a lifelong run's new goals) neither
    rebuild the graph nor search a goal twice. A goal's distances are searched when first asked
    for and the last ones are kept (up to `RECENT_BYTES`).

    Unguided (guidance None or unit costs): BFS steps (`array`: int32; rows int16 wherever no
    path can reach 32,767 steps, `grid.search_kernel.Searcher`). Guided: float64 least path
    costs (Dijkstra on the guidance's costs, `grid.guidance`). Either way `UNREACHABLE` (-1)
    marks obstacles and cells cut off from the goal in `array`; `row` gives the same distances
    as a flat read-only memoryview for the search loops, unreachable cells at `unreachable`
    (above any path)."""

    def __init__(self, blocked: np.ndarray, guidance=None):
        self.blocked = blocked
        self.shape = blocked.shape
        self.size = blocked.size
        if guidance is not None and guidance.is_unit:
            guidance = None  # unit costs are BFS steps: the integer tables, bit for bit
        self.guidance = guidance
        self.guided = guidance is not None
        self.step_costs = None if guidance is None else guidance.step_costs()
        # unguided: the compiled BFS (rows and bits in one pass); guided: `guided_kernel`
        self._searcher = None if self.guided else Searcher(blocked)
        self._guided_searcher = None  # built at the first guided search (`_search`)
        self.unreachable = float("inf") if self.guided else self._searcher.unreachable
        # one distance row per goal (the canonical copy), its packed bits, and a few -1 arrays
        self._rows: OrderedDict[int, np.ndarray] = OrderedDict()
        self._bits: OrderedDict[int, np.ndarray] = OrderedDict()
        self._arrays: OrderedDict[int, np.ndarray] = OrderedDict()
        row_bytes = 8 if self.guided else np.dtype(self._searcher.dtype).itemsize
        self.keep = max(16, RECENT_BYTES // (row_bytes * self.size))
        # -1 arrays and bits are handed on (bits to the observations, -1 arrays to callers that
        # want -1; the fleet's own goal choices read rows), not read tick after tick as rows
        # are: the last batch's and `RECENT_BYTES`' worth are kept
        self._recent_arrays = self.keep
        self._recent_bits = max(16, RECENT_BYTES // self.size)
        # goals searched only around one cell so far (unguided: bounded searches)
        self.windows = None if self.guided else Windows(self._searcher)
        self._lock = threading.Lock()
        self.searches = 0  # whole searches

    def move_targets(self) -> np.ndarray:
        """(H*W, 5) the flat cell each action leads to (`grid.actions.move_targets`), -1 also
        where the guidance forbids the move (a one-way lane): no rule or planner takes it."""
        targets = move_targets(self.blocked)
        if self.step_costs is not None:
            targets = np.where(np.isfinite(self.step_costs), targets, -1)
        return targets

    def _search(self, goals: list[int]) -> tuple[list[np.ndarray], list[np.ndarray | None]]:
        """Rows (unreachable at `unreachable`) and bits of `goals`, searched now."""
        self.searches += len(goals)
        if not self.guided:
            return self._searcher.search(goals)
        if self._guided_searcher is None:  # compiled: rows and bits at once
            self._guided_searcher = GuidedSearcher(self.blocked, self.step_costs)
        return self._guided_searcher.search(goals)

    def _keep(self, cache: OrderedDict, goal: int, value, keep: int) -> None:
        cache[goal] = value
        while len(cache) > keep:
            cache.popitem(last=False)

    def prepare(self, goals) -> None:
        """Search the flat `goals` not searched yet, all in one batch (the compiled search runs
        a batch on every core): a fleet's first tick or a lifelong tick's new goals."""
        with self._lock:
            missing = list(dict.fromkeys(int(g) for g in goals if int(g) not in self._rows))
        if missing:
            self._store(missing)

    def prepare_static(self, goals, statics, pad: int) -> None:
        """`prepare`, and each goal's padded static bytes (`search_kernel.fill_static`'s) into
        `statics` (one uint8 array of (H + 2 pad) * (W + 2 pad) per distinct goal): unguided,
        the search writes them itself (no bits array to touch, then copy: the observations'
        pool, `grid.goal_observer.GoalObserver`); guided, one batch, then the bits it kept."""
        goals = [int(g) for g in goals]
        if len(set(goals)) < len(goals):
            raise ValueError("prepare_static: a goal twice (one padded map each: distinct goals)")
        if self.guided:
            self.prepare(goals)
        with self._lock:
            fresh = [] if self.guided else [k for k, g in enumerate(goals) if g not in self._rows]
        if fresh:
            rows, _ = self._searcher.search([goals[k] for k in fresh],
                                            [statics[k] for k in fresh], pad)
            self.searches += len(fresh)
            self._remember([goals[k] for k in fresh], rows, [None] * len(fresh))
        blocked = self.blocked.reshape(-1).view(np.uint8)
        done = set(fresh)
        for k, g in enumerate(goals):
            if k not in done:
                fill_static(blocked, self.bits_row(g), statics[k], *self.shape, pad)

    def _store(self, goals: list[int]) -> list[np.ndarray]:
        rows, bits = self._search(goals)
        self._remember(goals, rows, bits)
        return rows

    def _remember(self, goals: list[int], rows, bits) -> None:
        with self._lock:
            self.keep = max(self.keep, len(goals))
            for goal, row, bit in zip(goals, rows, bits):
                if self.windows is not None:
                    self.windows.close([goal])  # the whole row supersedes it
                row.setflags(write=False)
                self._keep(self._rows, goal, row, self.keep)
                if bit is not None:
                    bit.setflags(write=False)
                    self._keep(self._bits, goal, bit, max(self._recent_bits, len(goals)))

    def reserve(self, goals: int) -> None:
        """Keep at least `goals` goals' distances (a fleet of N robots asks for N goals every
        tick: fewer kept would search them again and again), whatever `RECENT_BYTES` says."""
        with self._lock:
            self.keep = max(self.keep, int(goals))

    def _row(self, goal: int) -> np.ndarray:
        with self._lock:
            found = self._rows.get(goal)
            if found is not None:
                self._rows.move_to_end(goal)
                return found
        return self._store([goal])[0]

    def open_windows(self, goals, centres, half: int) -> None:
        """`Windows.open` for those of `goals` not searched whole (unguided tables only)."""
        if self.windows is None:
            raise ValueError("open_windows: bounded searches are for unguided tables (BFS steps)")
        with self._lock:
            whole = set(self._rows)
        self.windows.open(goals, centres, half, skip=whole)

    def whole(self, goal: int) -> np.ndarray:
        """Flat cell `goal`'s whole distance row (searched now if need be; `row`'s values)."""
        return self._row(int(goal))

    def row(self, goal: int):
        """Distances to flat cell `goal` as a flat read-only memoryview (Python ints for steps,
        floats for guided costs: what the search loops index cell by cell), unreachable cells
        and obstacles at `unreachable` (above any path). A goal only searched in a window so far
        (`windows`) gives a `WindowRow`: the same values, read from the window, and from a
        whole search once a read falls outside it."""
        goal = int(goal)
        with self._lock:
            window = None if goal in self._rows or self.windows is None \
                else self.windows.get(goal)
        if window is not None:
            return WindowRow(self, goal, window)
        return memoryview(self._row(goal))

    def array(self, goal: int) -> np.ndarray:
        """(H*W,) read-only distances to flat cell `goal` (`UNREACHABLE` where none)."""
        goal = int(goal)
        with self._lock:
            found = self._arrays.get(goal)
            if found is not None:
                self._arrays.move_to_end(goal)
                return found
        row = self._row(goal)
        # one new array (a guided row is float64 already: astype without copy=False made a
        # second, which doubled the -1 array's cost on large maps)
        found = np.where(row >= self.unreachable, UNREACHABLE, row).astype(
            np.float64 if self.guided else np.int32, copy=False)
        found.setflags(write=False)
        with self._lock:
            self._keep(self._arrays, goal, found, self._recent_arrays)
        return found

    def many(self, goals) -> np.ndarray:
        """(N, H, W) distances to each (row, col) goal of `goals` (N, 2), a copy."""
        goals = _as_goals(goals, self.shape)
        h, w = self.shape
        flat = (goals[:, 0] * w + goals[:, 1]).tolist()
        self.prepare(flat)
        out = np.empty((len(goals), h, w), dtype=np.float64 if self.guided else np.int32)
        for k, goal in enumerate(flat):
            row = self._row(goal).reshape(h, w)
            np.copyto(out[k], row)
            out[k][row >= self.unreachable] = UNREACHABLE
        return out

    def bits_row(self, goal: int) -> np.ndarray:
        """(H*W,) read-only packed heuristic bits to flat cell `goal` (`bits_of`'s, no copy)."""
        goal = int(goal)
        with self._lock:
            found = self._bits.get(goal)
            if found is not None:
                self._bits.move_to_end(goal)
                return found
        # never searched, or its bits dropped: the search gives both again
        rows, bits = self._search([goal])
        self._remember([goal], rows, bits)
        return bits[0]

    def bits_of(self, goals) -> np.ndarray:
        """(N, H, W) packed heuristic bits to each flat goal cell of `goals` (`bits`), from the
        search that found the distances."""
        flat = [int(g) for g in goals]
        self.prepare(flat)
        h, w = self.shape
        out = np.empty((len(flat), h, w), dtype=np.uint8)
        for k, goal in enumerate(flat):
            out[k] = self.bits_row(goal).reshape(h, w)
        return out

    def bits(self, dist: np.ndarray) -> np.ndarray:
        """Packed heuristic bits (N, H, W) uint8 from `many`'s distances: bit k where the move
        in direction k lies on a shortest path to the goal (unguided: one step closer)."""
        if not self.guided:
            return _bits_from_distances(dist)
        return _guided_bits(dist, self.step_costs.reshape(*self.shape, -1))


_TABLES: OrderedDict[tuple, DistanceTable] = OrderedDict()
_MAX_MAPS = 8
_LOCK = threading.Lock()  # fleet processes decide in threads
# the last searches of a map, kept up to this many bytes: the observations and the conflict rule
# ask for the same new goals within a tick
RECENT_BYTES = 64 << 20


def distance_table(grid, guidance=None) -> DistanceTable:
    """The shared `DistanceTable` of map `grid` ((H, W), nonzero = obstacle) under `guidance`
    (a `grid.guidance.Guidance` for this map, or None), kept for the last few maps."""
    blocked = _as_grid(grid)
    if guidance is not None and guidance.shape != blocked.shape:
        raise ValueError(f"guidance is for a {guidance.shape[0]}x{guidance.shape[1]} map, the "
                         f"map is {blocked.shape[0]}x{blocked.shape[1]}")
    key = (blocked.shape, np.packbits(blocked).tobytes(),
           None if guidance is None or guidance.is_unit else guidance.key)
    with _LOCK:
        table = _TABLES.get(key)
        if table is not None:
            _TABLES.move_to_end(key)
            return table
    table = DistanceTable(blocked, guidance)
    stream = _online_kind(guidance)
    with _LOCK:
        table = _TABLES.setdefault(key, table)
        if stream is not None:
            # online guidance: a new graph every period; a run reads only the newest (and, for
            # a tick, the one before): older tables of the stream are dead weight (rows of every
            # goal: 0.1 GB a table at 1,024 robots on 112x112)
            same = [k for k, t in _TABLES.items()
                    if k[:2] == key[:2] and _online_kind(t.guidance) == stream]
            for old in same[:-ONLINE_TABLES]:
                del _TABLES[old]
        while len(_TABLES) > _MAX_MAPS:
            _TABLES.popitem(last=False)
    return table


# tables kept per map of one online guidance stream (congestion, an online model)
ONLINE_TABLES = 2


def _online_kind(guidance) -> str | None:
    """The stream a graph of online guidance belongs to (its meta kind), None for static ones."""
    kind = None if guidance is None else guidance.meta.get("kind")
    return kind if kind in ("congestion", "online") else None


def _distances(blocked: np.ndarray, goals: np.ndarray, guidance=None) -> np.ndarray:
    return distance_table(blocked, guidance).many(goals)


def guided_distances_many(grid, goals, guidance=None) -> np.ndarray:
    """(N, H, W) distances to each goal under `guidance` (None: `bfs_distances_many`)."""
    blocked = _as_grid(grid)
    return _distances(blocked, _as_goals(goals, blocked.shape), guidance)


def bfs_distances(grid, goal) -> np.ndarray:
    """int32 (H, W) BFS steps from every cell to `goal`; `UNREACHABLE` (-1) for obstacles and cells
    cut off from the goal (and everywhere if the goal itself is an obstacle)."""
    blocked = _as_grid(grid)
    return _distances(blocked, _as_goals(goal, blocked.shape))[0]


def bfs_distances_many(grid, goals) -> np.ndarray:
    """int32 (N, H, W): `bfs_distances` for each of the N goals (one adjacency graph)."""
    blocked = _as_grid(grid)
    return _distances(blocked, _as_goals(goals, blocked.shape))


def _bits_from_distances(dist: np.ndarray) -> np.ndarray:
    """Packed heuristic bits (N, H, W) uint8 from distances (N, H, W)."""
    closer = dist - 1
    bits = np.zeros(dist.shape, dtype=np.uint8)
    # neighbour up of (r, c) is (r-1, c): compare dist[r-1] with dist[r] - 1, for r >= 1.
    up = dist[:, :-1, :]
    bits[:, 1:, :] |= ((up >= 0) & (up == closer[:, 1:, :])).astype(np.uint8)
    down = dist[:, 1:, :]
    bits[:, :-1, :] |= ((down >= 0) & (down == closer[:, :-1, :])).astype(np.uint8) << 1
    left = dist[:, :, :-1]
    bits[:, :, 1:] |= ((left >= 0) & (left == closer[:, :, 1:])).astype(np.uint8) << 2
    right = dist[:, :, 1:]
    bits[:, :, :-1] |= ((right >= 0) & (right == closer[:, :, :-1])).astype(np.uint8) << 3
    return bits


def _guided_bits(dist: np.ndarray, costs: np.ndarray) -> np.ndarray:
    """Packed heuristic bits (N, H, W) from guided distances (N, H, W) and step costs (H, W, 5):
    bit k where moving in direction k costs exactly what it saves (the move is on a least-cost
    path to the goal)."""
    n, h, w = dist.shape
    bits = np.zeros(dist.shape, dtype=np.uint8)
    pad = np.full((n, h + 2, w + 2), -1.0)
    pad[:, 1:-1, 1:-1] = dist
    here = dist
    for k, (dr, dc) in enumerate(((-1, 0), (1, 0), (0, -1), (0, 1))):
        there = pad[:, 1 + dr:1 + dr + h, 1 + dc:1 + dc + w]
        step = costs[None, :, :, k + 1]
        on_path = (here > 0) & (there >= 0) & np.isfinite(step) & np.isclose(step + there, here)
        bits |= on_path.astype(np.uint8) << k
    return bits


def unpack_heuristic_bits(bits: np.ndarray) -> np.ndarray:
    """(..., H, W) packed bits -> (..., 4, H, W) uint8 0/1 channels."""
    bits = np.asarray(bits, dtype=np.uint8)
    shifts = np.arange(NUM_HEURISTIC_CHANNELS, dtype=np.uint8).reshape(4, 1, 1)
    return (bits[..., None, :, :] >> shifts) & 1


def pack_heuristic_channels(channels: np.ndarray) -> np.ndarray:
    """(..., 4, H, W) 0/1 channels -> (..., H, W) packed uint8 bits."""
    channels = (np.asarray(channels) != 0).astype(np.uint8)
    return np.tensordot(channels, _BIT_WEIGHTS, axes=([-3], [0])).astype(np.uint8)


def heuristic_channels(grid, goal) -> np.ndarray:
    """uint8 (4, H, W) heuristic channels up/down/left/right for one goal (uncached)."""
    return unpack_heuristic_bits(_bits_from_distances(bfs_distances(grid, goal)[None]))[0]


class HeuristicCache:
    """Packed heuristic bits, and on request BFS distances, keyed by (map bytes, goal), LRU over
    maps.

    A map's adjacency graph is kept with its entries, and all goals missing for a request are
    searched in one call. `max_maps` bounds memory: one 80x80 map with 128 goals takes ~0.8 MB
    of bits, ~1.6 MB more once its distances were asked for (`distances`: the cost-to-go
    observation; the paper's observation never keeps them).
    """

    def __init__(self, max_maps: int = 64):
        if int(max_maps) < 1:
            raise ValueError(f"max_maps must be >= 1, got {max_maps}")
        self.max_maps = int(max_maps)
        self._maps: OrderedDict[tuple, tuple[dict, dict]] = OrderedDict()
        self.hits = 0
        self.misses = 0

    def clear(self) -> None:
        self._maps.clear()
        self.hits = self.misses = 0

    def bits(self, grid, goals, guidance=None) -> np.ndarray:
        """uint8 (N, H, W) packed heuristic bits for each goal of `goals` (N, 2) (`guidance`:
        a `grid.guidance.Guidance` for the map, None for BFS steps)."""
        return self._lookup(grid, goals, False, guidance)

    def distances(self, grid, goals, guidance=None) -> np.ndarray:
        """(N, H, W) distances to each goal of `goals` (N, 2): BFS steps as int16 when every
        distance of the map fits (else int32), guided costs as float32; the goals' bits are
        cached by the same search."""
        return self._lookup(grid, goals, True, guidance)

    def _lookup(self, grid, goals, want_distances: bool, guidance=None) -> np.ndarray:
        blocked = _as_grid(grid)
        goals = _as_goals(goals, blocked.shape)
        table = distance_table(blocked, guidance)
        key = (blocked.shape, np.packbits(blocked).tobytes(),
               table.guidance.key if table.guided else None)
        entry = self._maps.get(key)
        if entry is None:
            entry = ({}, {})
            self._maps[key] = entry
            while len(self._maps) > self.max_maps:
                self._maps.popitem(last=False)
        else:
            self._maps.move_to_end(key)
        bits_of, distances_of = entry
        wanted = distances_of if want_distances else bits_of
        goal_keys = [(int(r), int(c)) for r, c in goals]
        missing = sorted({g for g in goal_keys if g not in wanted})
        self.misses += len(missing)
        self.hits += len(goal_keys) - len(missing)
        if missing:
            h, w = blocked.shape
            computed = table.bits_of([r * w + c for r, c in missing])
            if want_distances:
                dist = compact_distances(table.many(np.array(missing, dtype=np.int64)))
            for k, g in enumerate(missing):
                computed[k].setflags(write=False)
                bits_of.setdefault(g, computed[k])
                if want_distances:
                    dist[k].setflags(write=False)
                    distances_of[g] = dist[k]
        return np.stack([wanted[g] for g in goal_keys]) if goal_keys else \
            np.empty((0, *blocked.shape), np.int32 if want_distances else np.uint8)

    def channels(self, grid, goals, guidance=None) -> np.ndarray:
        """uint8 (N, 4, H, W) heuristic channels for each goal."""
        return unpack_heuristic_bits(self.bits(grid, goals, guidance))


def compact_distances(distances: np.ndarray) -> np.ndarray:
    """`distances` as int16 when every value fits (maps of up to 32,767 free cells always do),
    else int32: the cost-to-go observation keeps one map per agent."""
    distances = np.asarray(distances)
    if np.issubdtype(distances.dtype, np.floating):  # guided costs
        return distances.astype(np.float32)
    if distances.size == 0 or int(distances.max()) < np.iinfo(np.int16).max:
        return distances.astype(np.int16)
    return distances.astype(np.int32, copy=False)


# The process-wide cache used by the environment.
default_cache = HeuristicCache()


def cached_heuristic_bits(grid, goals, guidance=None) -> np.ndarray:
    return default_cache.bits(grid, goals, guidance)


def cached_heuristic_channels(grid, goals, guidance=None) -> np.ndarray:
    return default_cache.channels(grid, goals, guidance)


def cached_distances(grid, goals, guidance=None) -> np.ndarray:
    return default_cache.distances(grid, goals, guidance)
