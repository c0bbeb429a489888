"""BFS distances to a goal over static obstacles and the four heuristic observation channels.

Distances come from scipy's compiled breadth-first search over the 4-connected free cells, its
visiting order cut into levels with numpy (a few ms per goal on 65k cells, about 3x faster than
its Dijkstra); a pure-Python BFS is what made the reference environments reset slowly.

Conventions:
- `bfs_distances` returns int32 steps to the goal; obstacle cells and free cells that cannot reach
  the goal hold `UNREACHABLE` (-1).
- Heuristic channel k (0 up, 1 down, 2 left, 3 right) is 1 at a cell when its neighbour in
  direction k is a free cell exactly one step closer to the goal (that is what "strictly closer"
  means with BFS distances). Obstacles, unreachable cells and the goal itself have no bit set.
- Internally the four channels are packed into one uint8 per cell (bit k = channel k): the
  environment gathers one byte per FOV cell instead of four, and the cache stays small.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import breadth_first_order

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


def _adjacency(blocked: np.ndarray) -> csr_matrix:
    """Symmetric 4-connected adjacency of the free cells."""
    h, w = blocked.shape
    free = ~blocked
    index = np.arange(h * w).reshape(h, w)
    horizontal = free[:, :-1] & free[:, 1:]
    vertical = free[:-1, :] & free[1:, :]
    rows = np.concatenate([index[:, :-1][horizontal], index[:-1, :][vertical]])
    cols = np.concatenate([index[:, 1:][horizontal], index[1:, :][vertical]])
    both = (np.concatenate([rows, cols]), np.concatenate([cols, rows]))
    # float64 and canonical, as scipy's graph searches want it: no conversion copy per search
    graph = csr_matrix((np.ones(2 * rows.size), both), shape=(h * w, h * w))
    graph.sum_duplicates()
    return graph


_MAPS: OrderedDict[tuple, tuple[csr_matrix, OrderedDict]] = OrderedDict()
_MAX_MAPS = 8
_LOCK = threading.Lock()  # fleet processes decide in threads
# the last searches of a map, kept up to this many bytes: the observations and the conflict rule
# ask for the same new goals within a tick
RECENT_BYTES = 64 << 20


def _map_entry(blocked: np.ndarray) -> tuple[csr_matrix, OrderedDict]:
    """(`_adjacency`, recent searches by goal cell) of a map, kept for the last few maps:
    callers that search one goal at a time (the conflict rules' distance tables, a fleet's goal
    checks, the observations of a lifelong run) neither rebuild the graph nor search twice."""
    key = (blocked.shape, np.packbits(blocked).tobytes())
    with _LOCK:
        entry = _MAPS.get(key)
        if entry is not None:
            _MAPS.move_to_end(key)
            return entry
    entry = (_adjacency(blocked), OrderedDict())
    with _LOCK:
        entry = _MAPS.setdefault(key, entry)
        while len(_MAPS) > _MAX_MAPS:
            _MAPS.popitem(last=False)
    return entry


def _bfs_steps(graph: csr_matrix, source: int, size: int) -> np.ndarray:
    """int32 (size,) BFS steps from `source` over `graph`, UNREACHABLE where not reached.

    A BFS visits its nodes level by level and discovers the children of earlier nodes first, so
    the position of each node's predecessor in the visiting order never decreases along it: level
    L+1 ends where that position first reaches the end of level L (one binary search a level)."""
    order, pred = breadth_first_order(graph, source, directed=True, return_predecessors=True)
    position = np.empty(size, dtype=np.int64)
    position[order] = np.arange(order.size)
    parent = position[pred[order[1:]]]  # non-decreasing
    ends, end, find = [1], 1, parent.searchsorted
    while end < order.size:
        end = int(find(end)) + 1
        ends.append(end)
    steps = np.full(size, UNREACHABLE, dtype=np.int32)
    steps[order] = np.repeat(np.arange(len(ends), dtype=np.int32), np.diff([0, *ends]))
    return steps


def _distances(blocked: np.ndarray, goals: np.ndarray, graph: csr_matrix | None = None) -> np.ndarray:
    h, w = blocked.shape
    dist = np.empty((goals.shape[0], h, w), dtype=np.int32)
    if goals.shape[0] == 0:
        return dist
    map_graph, recent = _map_entry(blocked)
    graph = map_graph if graph is None else graph
    keep = max(16, RECENT_BYTES // (4 * h * w))
    for k, (r, c) in enumerate(goals):
        if blocked[r, c]:  # a goal on an obstacle: report nothing as reachable
            dist[k] = UNREACHABLE
            continue
        cell = int(r) * w + int(c)
        with _LOCK:
            found = recent.get(cell)
            if found is not None:
                recent.move_to_end(cell)
        if found is None:
            found = _bfs_steps(graph, cell, h * w)
            with _LOCK:
                recent[cell] = found
                while len(recent) > keep:
                    recent.popitem(last=False)
        dist[k] = found.reshape(h, w)  # a copy: callers own what they get
    return dist


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
        self._maps: OrderedDict[tuple, tuple[csr_matrix, dict, dict]] = OrderedDict()
        self.hits = 0
        self.misses = 0

    def clear(self) -> None:
        self._maps.clear()
        self.hits = self.misses = 0

    def bits(self, grid, goals) -> np.ndarray:
        """uint8 (N, H, W) packed heuristic bits for each goal of `goals` (N, 2)."""
        return self._lookup(grid, goals, want_distances=False)

    def distances(self, grid, goals) -> np.ndarray:
        """(N, H, W) `bfs_distances` to each goal of `goals` (N, 2), int16 when every distance
        of the map fits (else int32); the goals' bits are cached by the same search."""
        return self._lookup(grid, goals, want_distances=True)

    def _lookup(self, grid, goals, want_distances: bool) -> np.ndarray:
        blocked = _as_grid(grid)
        goals = _as_goals(goals, blocked.shape)
        key = (blocked.shape, np.packbits(blocked).tobytes())
        entry = self._maps.get(key)
        if entry is None:
            entry = (_adjacency(blocked), {}, {})
            self._maps[key] = entry
            while len(self._maps) > self.max_maps:
                self._maps.popitem(last=False)
        else:
            self._maps.move_to_end(key)
        graph, bits_of, distances_of = entry
        wanted = distances_of if want_distances else bits_of
        goal_keys = [(int(r), int(c)) for r, c in goals]
        missing = sorted({g for g in goal_keys if g not in wanted})
        self.misses += len(missing)
        self.hits += len(goal_keys) - len(missing)
        if missing:
            dist = _distances(blocked, np.array(missing, dtype=np.int64), graph)
            computed = _bits_from_distances(dist)
            if want_distances:
                dist = compact_distances(dist)
            for k, g in enumerate(missing):
                computed[k].setflags(write=False)
                bits_of.setdefault(g, computed[k])
                if want_distances:
                    dist[k].setflags(write=False)
                    distances_of[g] = dist[k]
        return np.stack([wanted[g] for g in goal_keys]) if goal_keys else \
            np.empty((0, *blocked.shape), np.int32 if want_distances else np.uint8)

    def channels(self, grid, goals) -> np.ndarray:
        """uint8 (N, 4, H, W) heuristic channels for each goal."""
        return unpack_heuristic_bits(self.bits(grid, goals))


def compact_distances(distances: np.ndarray) -> np.ndarray:
    """`distances` as int16 when every value fits (maps of up to 32,767 free cells always do),
    else int32: the cost-to-go observation keeps one map per agent."""
    distances = np.asarray(distances)
    if distances.size == 0 or int(distances.max()) < np.iinfo(np.int16).max:
        return distances.astype(np.int16)
    return distances.astype(np.int32, copy=False)


# The process-wide cache used by the environment.
default_cache = HeuristicCache()


def cached_heuristic_bits(grid, goals) -> np.ndarray:
    return default_cache.bits(grid, goals)


def cached_heuristic_channels(grid, goals) -> np.ndarray:
    return default_cache.channels(grid, goals)


def cached_distances(grid, goals) -> np.ndarray:
    return default_cache.distances(grid, goals)
