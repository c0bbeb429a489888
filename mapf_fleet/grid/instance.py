"""MAPF instances, the seeded instance generator of the paper's protocol, and the DHC test sets."""

from __future__ import annotations

import dataclasses
from os import PathLike
from pathlib import Path

import numpy as np
from scipy import ndimage

from .errors import InstanceError, MapFormatError

# 4-connectivity: agents move up/down/left/right only.
_FOUR_CONNECTED = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=bool)

# Training density: triangular(0, 0.33, 0.5) as in the DHC/DCC reference code.
TRAINING_DENSITY = (0.0, 0.33, 0.5)


def as_rng(rng) -> np.random.Generator:
    """A numpy Generator from a Generator, an int seed or None."""
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None or isinstance(rng, (int, np.integer)):
        return np.random.default_rng(rng)
    raise TypeError(f"rng must be a numpy.random.Generator or an int seed, got {type(rng).__name__}")


def free_components(grid: np.ndarray) -> np.ndarray:
    """int32 (H, W) labels of the 4-connected free regions: 0 on obstacles, 1..K on free cells."""
    labels, _ = ndimage.label(np.asarray(grid) == 0, structure=_FOUR_CONNECTED)
    return labels.astype(np.int32, copy=False)


@dataclasses.dataclass(frozen=True, eq=False)
class Instance:
    """A map and one (start, goal) pair per agent.

    grid: uint8 (H, W), 1 = obstacle. starts, goals: int64 (N, 2) in (row, col).
    Construction coerces the arrays and checks their shapes; `validate()` checks the cells
    (inside the map, free, not shared, goal reachable from start). Starts may coincide with other
    agents' goals (a valid MAPF instance); the generator never produces that.
    """

    grid: np.ndarray
    starts: np.ndarray
    goals: np.ndarray

    def __post_init__(self):
        grid = np.asarray(self.grid)
        if grid.ndim != 2 or grid.shape[0] == 0 or grid.shape[1] == 0:
            raise InstanceError(f"grid must be a non-empty 2-D array, got shape {grid.shape}")
        if not np.isin(grid, (0, 1)).all():
            raise InstanceError("grid must hold only 0 (free) and 1 (obstacle)")
        grid = grid.astype(np.uint8)
        arrays = {}
        for name in ("starts", "goals"):
            value = np.asarray(getattr(self, name))
            if value.size == 0:
                value = value.reshape(0, 2)
            if value.ndim != 2 or value.shape[1] != 2:
                raise InstanceError(f"{name} must have shape (N, 2), got {value.shape}")
            if not np.issubdtype(value.dtype, np.integer):
                if not np.all(np.equal(np.mod(value, 1), 0)):
                    raise InstanceError(f"{name} must hold integer (row, col) cells")
            arrays[name] = value.astype(np.int64)
        if arrays["starts"].shape != arrays["goals"].shape:
            raise InstanceError(f"starts {arrays['starts'].shape} and goals "
                                f"{arrays['goals'].shape} differ in number of agents")
        for name, value in (("grid", grid), *arrays.items()):
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    @property
    def num_agents(self) -> int:
        return int(self.starts.shape[0])

    @property
    def size(self) -> tuple[int, int]:
        """(height, width) of the map."""
        return (int(self.grid.shape[0]), int(self.grid.shape[1]))

    def validate(self) -> "Instance":
        """Raise `InstanceError` naming the first bad agent and cell; return self when valid."""
        h, w = self.size
        for name, cells in (("start", self.starts), ("goal", self.goals)):
            outside = (cells[:, 0] < 0) | (cells[:, 0] >= h) | (cells[:, 1] < 0) | (cells[:, 1] >= w)
            if outside.any():
                i = int(np.flatnonzero(outside)[0])
                raise InstanceError(f"{name} is outside the {h}x{w} map", i, tuple(cells[i]))
            blocked = self.grid[cells[:, 0], cells[:, 1]] != 0
            if blocked.any():
                i = int(np.flatnonzero(blocked)[0])
                raise InstanceError(f"{name} is on an obstacle", i, tuple(cells[i]))
            flat = cells[:, 0] * w + cells[:, 1]
            _, first, counts = np.unique(flat, return_index=True, return_counts=True)
            if (counts > 1).any():
                shared = flat[first[counts > 1][0]]
                agents = np.flatnonzero(flat == shared)
                raise InstanceError(f"{name} is shared with agent(s) {agents[1:].tolist()}",
                                    int(agents[0]), divmod(int(shared), w))
        labels = free_components(self.grid)
        start_label = labels[self.starts[:, 0], self.starts[:, 1]]
        goal_label = labels[self.goals[:, 0], self.goals[:, 1]]
        cut = start_label != goal_label
        if cut.any():
            i = int(np.flatnonzero(cut)[0])
            raise InstanceError(f"goal is unreachable from start {tuple(self.starts[i].tolist())}",
                                i, tuple(self.goals[i]))
        return self

    def __eq__(self, other):
        if not isinstance(other, Instance):
            return NotImplemented
        return (np.array_equal(self.grid, other.grid) and np.array_equal(self.starts, other.starts)
                and np.array_equal(self.goals, other.goals))

    __hash__ = None


def sample_training_density(rng) -> float:
    """Obstacle density for a training map: triangular(0, 0.33, 0.5)."""
    low, mode, high = TRAINING_DENSITY
    return float(as_rng(rng).triangular(low, mode, high))


def random_grid(size, density: float, rng) -> np.ndarray:
    """uint8 map where each cell is an obstacle with probability `density`."""
    h, w = (size, size) if np.isscalar(size) else tuple(size)
    return (as_rng(rng).random((int(h), int(w))) < density).astype(np.uint8)


def generate_instance(size, num_agents: int, density: float, rng, max_map_attempts: int = 100
                      ) -> Instance:
    """A random instance by the DHC reference protocol, reproducible from `rng` (Generator or seed).

    Each cell is an obstacle with probability `density`. Each agent in turn picks a free
    4-connected region with probability proportional to its unused cells (among regions with at
    least two unused cells), i.e. its start is uniform over the usable free cells, then two
    distinct unused cells of that region as start and goal. The DHC training code picks regions
    uniformly, which crowds agents into small pockets: a small region is as likely as the largest,
    so far more agents start outside the largest region than in the published DHC test sets;
    weighting by size matches them (docs/results.md, "The generated instances against the
    published ones"). So all 2N starts and goals are distinct and each goal is reachable from its
    start. A map without room for N pairs is redrawn
    (up to `max_map_attempts` times). `size` is an int (square) or (height, width).
    """
    rng = as_rng(rng)
    num_agents = int(num_agents)
    if num_agents < 0:
        raise ValueError(f"num_agents must be >= 0, got {num_agents}")
    if not 0.0 <= float(density) < 1.0:
        raise ValueError(f"density must be in [0, 1), got {density}")
    h, w = (size, size) if np.isscalar(size) else tuple(size)
    if int(h) < 1 or int(w) < 1:
        raise ValueError(f"size must be positive, got {size}")
    if 2 * num_agents > int(h) * int(w):
        raise ValueError(f"a {h}x{w} map cannot hold {num_agents} start/goal pairs")
    for _ in range(max_map_attempts):
        grid = random_grid((h, w), density, rng)
        labels = free_components(grid)
        order = np.argsort(labels.ravel(), kind="stable")
        counts = np.bincount(labels.ravel())
        bounds = np.concatenate([[0], np.cumsum(counts)])
        # cells of region k (k >= 1), in random order; consumed two at a time from the end
        regions = [rng.permutation(order[bounds[k]:bounds[k + 1]]) for k in range(1, counts.size)]
        if sum(len(r) // 2 for r in regions) < num_agents:
            continue
        remaining = [len(r) for r in regions]
        open_regions = [k for k, n in enumerate(remaining) if n >= 2]
        starts = np.empty(num_agents, dtype=np.int64)
        goals = np.empty(num_agents, dtype=np.int64)
        for agent in range(num_agents):
            weights = np.array([remaining[k] for k in open_regions], dtype=np.float64)
            slot = int(rng.choice(len(open_regions), p=weights / weights.sum()))
            k = open_regions[slot]
            n = remaining[k]
            starts[agent], goals[agent] = regions[k][n - 1], regions[k][n - 2]
            remaining[k] = n - 2
            if remaining[k] < 2:
                open_regions.pop(slot)
        return Instance(grid, np.stack(np.divmod(starts, w), axis=1),
                        np.stack(np.divmod(goals, w), axis=1))
    raise InstanceError(f"no {h}x{w} map with density {density} had room for {num_agents} agents "
                        f"in {max_map_attempts} attempts")


def load_dhc_testset(path: str | PathLike) -> list[Instance]:
    """The DHC authors' published test instances: an .npz with `maps` (M, H, W) uint8 and
    `starts`, `goals` (M, N, 2) in (row, col). Each instance is validated; a bad one raises
    `MapFormatError` naming the file and the instance index."""
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise
    except Exception as exc:  # zip/format errors from numpy
        raise MapFormatError(path, None, f"not a readable .npz file ({exc})") from exc
    with data:
        missing = [k for k in ("maps", "starts", "goals") if k not in data.files]
        if missing:
            raise MapFormatError(path, None, f"missing array(s) {missing}; found {data.files}")
        maps, starts, goals = data["maps"], data["starts"], data["goals"]
    if maps.ndim != 3 or starts.ndim != 3 or goals.ndim != 3 or starts.shape[-1] != 2 \
            or not (len(maps) == len(starts) == len(goals)) or starts.shape != goals.shape:
        raise MapFormatError(path, None, f"inconsistent shapes: maps {maps.shape}, "
                                         f"starts {starts.shape}, goals {goals.shape}")
    instances = []
    for index in range(len(maps)):
        try:
            instances.append(Instance(maps[index], starts[index], goals[index]).validate())
        except InstanceError as exc:
            raise MapFormatError(path, None, f"instance {index}: {exc}") from exc
    return instances
