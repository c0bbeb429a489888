"""Structured map families beside the paper's random maps, and a training mix over them.

Kinds (`MAP_KINDS`):
  - "random":    the paper's maps (`instance.generate_instance`), density drawn from the training
                 triangular(0, 0.33, 0.5) unless `density=` is given;
  - "maze":      corridors of width 1 or 2 (`corridor_width=`; drawn from `MAZE_WIDTHS` when not
                 given) between walls of thickness 1: a random spanning tree of the corridor
                 lattice (scipy's minimum spanning tree over random weights) plus a fraction
                 `loop_fraction` of the other walls opened, so there are cycles where agents can
                 pass each other. Wall junctions ("posts") are never opened, so no free
                 (w+1)x(w+1) square exists: the corridors are exactly w wide;
  - "rooms":     square rooms of interior side about `room_size` (drawn from `ROOM_SIZES`)
                 behind walls of thickness 1, joined by doors of width `door_width` in the
                 shared walls: a random spanning tree of the room graph plus a fraction
                 `extra_door_fraction` of the other walls;
  - "warehouse": shelf blocks (`shelf_depth` rows x `shelf_length` columns, obstacles) in a
                 regular layout, separated by aisles of `aisle_width` rows between block rows and
                 cross aisles of `cross_aisle_width` columns, with a free border of the
                 cross-aisle width; parameters not given are drawn from `WAREHOUSE_CHOICES`.

One more kind, `DENSE` ("dense"), outside `MAP_KINDS` (the training mix `TaskMix` and the demo
datasets keep their four kinds): the small crowded random maps learned MAPF is compared on
(17-21 cells a side with 32-64 agents, MAPF-GPT's "random" set). `size` is the largest side: the
map's side is drawn uniformly from size - 4 .. size (`DENSE_SIDE_SPREAD`), a "random" map at that
side (same density rule), and the grid is padded to size x size with obstacles. Padding is exact:
the environment pads off-map cells as obstacles, so the observations, the moves, PIBT and LaCAM
are the same as on the unpadded map, and instances of one size stack into one array.

Every structured map has one 4-connected free region (tested). Agents' starts and goals are 2N
distinct cells drawn uniformly from the largest free region; the instance is checked with
`Instance.validate()`. All randomness comes from `rng` (a numpy Generator or an int seed), so a
seed gives the same instance every time.

`capacity(kind, size)` is the number of agents every map of that kind and size (default parameter
choices) can hold, from the minimal maps (tree openings only). `TaskMix` is the training mix
(kinds with weights, sizes, agent counts), checked against these capacities, and
`sample_task_instance(mix, rng)` draws one task from it.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from typing import Any

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import minimum_spanning_tree

from .errors import InstanceError
from .instance import Instance, as_rng, free_components, generate_instance, sample_training_density

MAP_KINDS = ("random", "maze", "rooms", "warehouse")
MIN_STRUCTURED_SIZE = 8  # smallest side of a structured map
MAZE_WIDTHS = (1, 2)
ROOM_SIZES = (4, 5, 6, 7, 8)
WAREHOUSE_CHOICES = {
    "shelf_depth": (1, 2),
    "shelf_length": (3, 4, 5, 6, 8),
    "aisle_width": (1, 2),
    "cross_aisle_width": (1, 2, 3),
}
# "random" maps have density <= 0.5 (training triangular); capacity is taken as a quarter of the
# cells (half the expected free cells at the highest density). generate_instance redraws maps
# that cannot hold the agents, so this is a sizing rule, not a guarantee.
RANDOM_CAPACITY_FRACTION = 0.25
DENSE = "dense"
DENSE_SIDE_SPREAD = 4  # a "dense" map of size S has a side drawn from S - 4 .. S
GENERATED_KINDS = MAP_KINDS + (DENSE,)  # every kind generate_kind_instance makes


def _dims(size) -> tuple[int, int]:
    h, w = (size, size) if np.isscalar(size) else tuple(size)
    if isinstance(h, bool) or isinstance(w, bool) or int(h) != h or int(w) != w:
        raise ValueError(f"size must be an int or (height, width) of ints, got {size!r}")
    h, w = int(h), int(w)
    if h < MIN_STRUCTURED_SIZE or w < MIN_STRUCTURED_SIZE:
        raise ValueError(f"size {size!r}: structured maps need sides >= {MIN_STRUCTURED_SIZE}")
    return h, w


def _choice(rng: np.random.Generator, value, choices, name: str) -> int:
    if value is None:
        return int(choices[int(rng.integers(len(choices)))])
    if isinstance(value, bool) or int(value) != value or int(value) < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


def _fraction(value, name: str) -> float:
    if not 0.0 <= float(value) <= 1.0:
        raise ValueError(f"{name} must be in [0, 1], got {value!r}")
    return float(value)


def _lattice_edges(rows: int, cols: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edges of a rows x cols 4-connected lattice of nodes i * cols + j: (u, v, horizontal)."""
    node = np.arange(rows * cols).reshape(rows, cols)
    hu, hv = node[:, :-1].ravel(), node[:, 1:].ravel()  # (i, j) - (i, j + 1)
    vu, vv = node[:-1, :].ravel(), node[1:, :].ravel()  # (i, j) - (i + 1, j)
    horizontal = np.concatenate([np.ones(hu.size, bool), np.zeros(vu.size, bool)])
    return np.concatenate([hu, vu]), np.concatenate([hv, vv]), horizontal


def _open_edges(rng: np.random.Generator, num_nodes: int, u: np.ndarray, v: np.ndarray,
                extra_fraction: float) -> np.ndarray:
    """bool (E,): a random spanning tree of the graph (MST over random weights) plus each other
    edge with probability `extra_fraction`. Draws the same random numbers whatever the outcome."""
    weights = 1.0 + rng.random(u.size)  # > 0: scipy reads 0 as "no edge"
    extra = rng.random(u.size) < extra_fraction
    if u.size == 0:
        return extra
    graph = sparse.coo_matrix((weights, (u, v)), shape=(num_nodes, num_nodes)).tocsr()
    tree = minimum_spanning_tree(graph).tocoo()
    in_tree = np.zeros((num_nodes, num_nodes), bool)
    in_tree[tree.row, tree.col] = True
    return in_tree[u, v] | in_tree[v, u] | extra


# -- map generators -------------------------------------------------------------------------------
def maze_grid(size, rng, corridor_width: int | None = None, loop_fraction: float = 0.1
              ) -> np.ndarray:
    """uint8 maze: corridor cells of w x w (w = `corridor_width`, 1 or 2) on a lattice of pitch
    w + 1, walls of thickness 1; a random spanning tree of openings plus `loop_fraction` of the
    remaining walls. The lattice is centred; rows/columns it does not fill stay obstacles."""
    rng = as_rng(rng)
    h, w = _dims(size)
    width = _choice(rng, corridor_width, MAZE_WIDTHS, "corridor_width")
    if width not in MAZE_WIDTHS:
        raise ValueError(f"corridor_width must be one of {MAZE_WIDTHS}, got {corridor_width!r}")
    loop_fraction = _fraction(loop_fraction, "loop_fraction")
    pitch = width + 1
    rows, cols = (h - 1) // pitch, (w - 1) // pitch
    grid = np.ones((h, w), np.uint8)
    if rows < 1 or cols < 1:
        raise ValueError(f"size {size!r} holds no maze cell of width {width}")
    # first row/column of each lattice cell; the maze is centred, spare rows/columns are walls
    starts_r = 1 + (h - 1 - rows * pitch) // 2 + pitch * np.arange(rows)
    starts_c = 1 + (w - 1 - cols * pitch) // 2 + pitch * np.arange(cols)
    inside_r = np.zeros(h, bool)
    inside_c = np.zeros(w, bool)
    for k in range(width):
        inside_r[starts_r + k] = True
        inside_c[starts_c + k] = True
    grid[np.ix_(inside_r, inside_c)] = 0
    u, v, horizontal = _lattice_edges(rows, cols)
    opened = _open_edges(rng, rows * cols, u, v, loop_fraction)
    for a, is_h in zip(u[opened], horizontal[opened]):
        i, j = divmod(int(a), cols)
        r, c = int(starts_r[i]), int(starts_c[j])
        if is_h:  # wall column right of cell (i, j)
            grid[r:r + width, c + width] = 0
        else:  # wall row below cell (i, j)
            grid[r + width, c:c + width] = 0
    return grid


def _wall_lines(length: int, interior: int) -> np.ndarray:
    """Wall positions 0 .. length-1 spaced evenly, rooms of about `interior` cells between."""
    count = max(1, int(round((length - 1) / (interior + 1))))
    return np.linspace(0, length - 1, count + 1).round().astype(np.int64)


def rooms_grid(size, rng, room_size: int | None = None, door_width: int = 1,
               extra_door_fraction: float = 0.3) -> np.ndarray:
    """uint8 map of rooms (interior side about `room_size`) with walls of thickness 1 (the border
    included) and doors of `door_width` cells (cut to the wall's length) joining neighbouring
    rooms: a random spanning tree of doors plus `extra_door_fraction` of the other walls."""
    rng = as_rng(rng)
    h, w = _dims(size)
    interior = _choice(rng, room_size, ROOM_SIZES, "room_size")
    door = _choice(rng, door_width, (1,), "door_width")
    extra_door_fraction = _fraction(extra_door_fraction, "extra_door_fraction")
    wall_r, wall_c = _wall_lines(h, interior), _wall_lines(w, interior)
    grid = np.zeros((h, w), np.uint8)
    grid[wall_r, :] = 1
    grid[:, wall_c] = 1
    rows, cols = wall_r.size - 1, wall_c.size - 1
    u, v, horizontal = _lattice_edges(rows, cols)
    opened = _open_edges(rng, rows * cols, u, v, extra_door_fraction)
    offsets = rng.random(u.size)  # where along its wall each door goes (drawn for every wall)
    for a, is_h, offset in zip(u[opened], horizontal[opened], offsets[opened]):
        i, j = divmod(int(a), cols)
        if is_h:  # wall column wall_c[j + 1], rows inside room row i
            lo, hi, line = int(wall_r[i]) + 1, int(wall_r[i + 1]) - 1, int(wall_c[j + 1])
        else:  # wall row wall_r[i + 1], columns inside room column j
            lo, hi, line = int(wall_c[j]) + 1, int(wall_c[j + 1]) - 1, int(wall_r[i + 1])
        span = min(door, hi - lo + 1)
        first = lo + int(offset * (hi - lo + 2 - span))
        if is_h:
            grid[first:first + span, line] = 0
        else:
            grid[line, first:first + span] = 0
    return grid


def warehouse_grid(size, rng, shelf_depth: int | None = None, shelf_length: int | None = None,
                   aisle_width: int | None = None, cross_aisle_width: int | None = None
                   ) -> np.ndarray:
    """uint8 warehouse: shelf blocks of `shelf_depth` x `shelf_length` obstacle cells in rows
    separated by `aisle_width` free rows, blocks in a row separated by `cross_aisle_width` free
    columns, a free border `cross_aisle_width` wide. Parameters not given are drawn from
    `WAREHOUSE_CHOICES`. The layout is centred; a map too small for one block is all free."""
    rng = as_rng(rng)
    h, w = _dims(size)
    depth = _choice(rng, shelf_depth, WAREHOUSE_CHOICES["shelf_depth"], "shelf_depth")
    length = _choice(rng, shelf_length, WAREHOUSE_CHOICES["shelf_length"], "shelf_length")
    aisle = _choice(rng, aisle_width, WAREHOUSE_CHOICES["aisle_width"], "aisle_width")
    cross = _choice(rng, cross_aisle_width, WAREHOUSE_CHOICES["cross_aisle_width"],
                    "cross_aisle_width")
    grid = np.zeros((h, w), np.uint8)
    block_rows = max(0, (h - 2 * cross + aisle) // (depth + aisle))
    block_cols = max(0, (w - 2 * cross + cross) // (length + cross))
    if block_rows == 0 or block_cols == 0:
        return grid
    used_h = block_rows * (depth + aisle) - aisle
    used_w = block_cols * (length + cross) - cross
    top, left = (h - used_h) // 2, (w - used_w) // 2
    for i in range(block_rows):
        r = top + i * (depth + aisle)
        for j in range(block_cols):
            c = left + j * (length + cross)
            grid[r:r + depth, c:c + length] = 1
    return grid


MAP_GENERATORS = {"maze": maze_grid, "rooms": rooms_grid, "warehouse": warehouse_grid}

# parameters that add openings beyond the minimal (tree) map; 0 gives the minimal map
_EXTRA_OPENINGS = {"maze": "loop_fraction", "rooms": "extra_door_fraction"}
_DRAWN = {"maze": {"corridor_width": MAZE_WIDTHS}, "rooms": {"room_size": ROOM_SIZES},
          "warehouse": WAREHOUSE_CHOICES}


def generate_map(kind: str, size, rng, **params) -> np.ndarray:
    """uint8 (H, W) map of a structured `kind` ("maze", "rooms", "warehouse")."""
    if kind not in MAP_GENERATORS:
        raise ValueError(f"map kind must be one of {tuple(MAP_GENERATORS)}, got {kind!r}")
    try:
        return MAP_GENERATORS[kind](size, rng, **params)
    except TypeError as exc:  # unknown keyword
        raise ValueError(f"map kind {kind!r}: {exc}") from None


def place_agents(grid: np.ndarray, num_agents: int, rng) -> Instance:
    """An instance on `grid` with 2N distinct start/goal cells drawn uniformly from its largest
    free 4-connected region; validated. Raises InstanceError when the region is too small."""
    rng = as_rng(rng)
    num_agents = int(num_agents)
    if num_agents < 0:
        raise ValueError(f"num_agents must be >= 0, got {num_agents}")
    grid = np.asarray(grid, np.uint8)
    labels = free_components(grid)
    counts = np.bincount(labels.ravel())
    counts[0] = 0
    largest = int(counts.argmax())
    cells = np.flatnonzero(labels.ravel() == largest) if largest else np.empty(0, np.int64)
    if 2 * num_agents > cells.size:
        raise InstanceError(f"the largest free region of this {grid.shape[0]}x{grid.shape[1]} map "
                            f"has {cells.size} cells: no room for {num_agents} start/goal pairs")
    chosen = rng.choice(cells, size=2 * num_agents, replace=False)
    rc = np.stack(np.divmod(chosen, grid.shape[1]), axis=1)
    return Instance(grid, rc[:num_agents], rc[num_agents:]).validate()


def generate_kind_instance(kind: str, size, num_agents: int, rng, **params) -> Instance:
    """A validated instance of map `kind` (one of `MAP_KINDS`), `size` (int or (H, W)) and
    `num_agents`, reproducible from `rng`. `params` go to the map generator ("random": `density`,
    default drawn from the training triangular distribution)."""
    rng = as_rng(rng)
    if kind in ("random", DENSE):
        unknown = set(params) - {"density"}
        if unknown:
            raise ValueError(f"map kind {kind!r}: unknown parameter(s) {sorted(unknown)}")
        density = params.get("density")
        density = sample_training_density(rng) if density is None else float(density)
        if kind == DENSE:
            return dense_instance(size, num_agents, density, rng)
        return generate_instance(size, num_agents, density, rng).validate()
    return place_agents(generate_map(kind, size, rng, **params), num_agents, rng)


def dense_instance(size: int, num_agents: int, density: float, rng) -> Instance:
    """A "dense" instance (module docstring): a random map of side drawn from
    size - DENSE_SIDE_SPREAD .. size, padded with obstacles to size x size."""
    rng = as_rng(rng)
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) \
            or size <= DENSE_SIDE_SPREAD:
        raise ValueError(f"map kind {DENSE!r}: size must be an integer > {DENSE_SIDE_SPREAD}, "
                         f"got {size!r}")
    side = int(size) - int(rng.integers(DENSE_SIDE_SPREAD + 1))
    inner = generate_instance(side, num_agents, density, rng)
    grid = np.ones((int(size), int(size)), np.uint8)
    grid[:side, :side] = inner.grid
    return Instance(grid, inner.starts, inner.goals).validate()


@functools.lru_cache(maxsize=None)
def capacity(kind: str, size: int) -> int:
    """Agents that every map of `kind` and side `size` holds with the default parameter draws:
    half the free cells of the smallest minimal map (tree openings only, every drawn parameter
    combination). "random": `RANDOM_CAPACITY_FRACTION` of the cells (a sizing rule)."""
    if kind == "random":
        return int(RANDOM_CAPACITY_FRACTION * size * size)
    if kind == DENSE:  # the smallest side it may draw
        return int(RANDOM_CAPACITY_FRACTION * (size - DENSE_SIDE_SPREAD) ** 2)
    if kind not in MAP_GENERATORS:
        raise ValueError(f"map kind must be one of {MAP_KINDS}, got {kind!r}")
    drawn = _DRAWN[kind]
    fewest = None
    for values in itertools.product(*drawn.values()):
        params = dict(zip(drawn, values))
        if kind in _EXTRA_OPENINGS:
            params[_EXTRA_OPENINGS[kind]] = 0.0
        grid = generate_map(kind, size, 0, **params)
        labels = free_components(grid)
        free = int(np.bincount(labels.ravel())[1:].max(initial=0))
        fewest = free if fewest is None else min(fewest, free)
    return fewest // 2


# -- training mix ---------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class TaskMix:
    """Training tasks: a map kind drawn by `kinds` weights, then a side from `sizes` and an agent
    count from `agents`, each uniformly. Every (kind with weight > 0, size, agents) combination
    must fit: agents <= capacity(kind, size)."""

    kinds: dict
    sizes: tuple
    agents: tuple

    def __post_init__(self):
        if not isinstance(self.kinds, dict) or not self.kinds:
            raise ValueError(f"kinds = {self.kinds!r}: must be a non-empty mapping kind -> weight")
        for kind, weight in self.kinds.items():
            if kind not in MAP_KINDS:
                raise ValueError(f"kinds: unknown map kind {kind!r} (known: {', '.join(MAP_KINDS)})")
            if isinstance(weight, bool) or not isinstance(weight, (int, float)) \
                    or not np.isfinite(weight) or weight < 0:
                raise ValueError(f"kinds: weight of {kind!r} = {weight!r}: must be a number >= 0")
        if sum(self.kinds.values()) <= 0:
            raise ValueError(f"kinds = {self.kinds!r}: weights must not all be 0")
        for name, low in (("sizes", MIN_STRUCTURED_SIZE), ("agents", 1)):
            values = getattr(self, name)
            if not isinstance(values, (list, tuple)) or not values:
                raise ValueError(f"{name} = {values!r}: must be a non-empty list of integers")
            for value in values:
                if isinstance(value, bool) or not isinstance(value, (int, np.integer)) \
                        or value < low:
                    raise ValueError(f"{name}: entry {value!r} must be an integer >= {low}")
            object.__setattr__(self, name, tuple(int(v) for v in values))
        for kind, weight in self.kinds.items():
            if weight <= 0:
                continue
            for size in self.sizes:
                room = capacity(kind, size)
                if max(self.agents) > room:
                    raise ValueError(f"agents: {max(self.agents)} agents do not fit every "
                                     f"{kind} map of size {size} (at most {room})")

    @classmethod
    def from_dict(cls, data: Any) -> "TaskMix":
        if not isinstance(data, dict):
            raise ValueError(f"must be a mapping with kinds, sizes, agents; got {data!r}")
        missing = [k for k in ("kinds", "sizes", "agents") if k not in data]
        unknown = sorted(set(data) - {"kinds", "sizes", "agents"})
        if missing or unknown:
            raise ValueError(f"needs keys kinds, sizes, agents; missing {missing}, unknown {unknown}")
        return cls(dict(data["kinds"]) if isinstance(data["kinds"], dict) else data["kinds"],
                   data["sizes"], data["agents"])

    def to_dict(self) -> dict:
        return {"kinds": dict(self.kinds), "sizes": list(self.sizes), "agents": list(self.agents)}

    def kind_probabilities(self) -> tuple[tuple[str, ...], np.ndarray]:
        names = tuple(self.kinds)
        weights = np.array([float(self.kinds[k]) for k in names])
        return names, weights / weights.sum()


@dataclasses.dataclass(frozen=True)
class TaskInstance:
    kind: str
    size: int
    num_agents: int
    instance: Instance


def sample_task_instance(mix: TaskMix | dict, rng) -> TaskInstance:
    """Draw a kind (by weight), a size and an agent count (uniformly) from `mix`, then a
    validated instance of them; reproducible from `rng`."""
    mix = mix if isinstance(mix, TaskMix) else TaskMix.from_dict(mix)
    rng = as_rng(rng)
    names, probs = mix.kind_probabilities()
    kind = names[int(rng.choice(len(names), p=probs))]
    size = mix.sizes[int(rng.integers(len(mix.sizes)))]
    agents = mix.agents[int(rng.integers(len(mix.agents)))]
    return TaskInstance(kind, size, agents, generate_kind_instance(kind, size, agents, rng))
