"""Guidance graphs: a cost per directed edge and per wait on a grid map (numpy and scipy only).

A guidance graph changes what "distance to the goal" means for everything that reads one: the
PIBT rules' candidate order, the planning arbiter's heuristic, the heuristic channels of the
DHC/DCC observation, the simulator's and the aggregator's distances. The distance from a cell to
a goal is the least total cost of a path under the graph's costs (Dijkstra per goal,
`heuristic.DistanceTable`), instead of the number of steps (BFS). Costs that make a cell's
crossing dearer in one direction than the other spread traffic and keep opposite streams apart
(one-way lanes), which is where a fleet's throughput comes from in the field (GGO, Zhang et al.,
IJCAI 2024; the League of Robot Runners 2024 ablation: docs/results.md, "Continuous operation
with guidance").

`costs[r, c, a]` is the cost of taking action `a` (DHC order: 0 wait, 1 up, 2 down, 3 left,
4 right) from cell (r, c). Every move that stays on the map between free cells has a finite
cost > 0, or `inf` to forbid it (a one-way lane); moves off the map or into an obstacle are
ignored (stored as `inf`). The wait cost is what PIBT compares a wait with (wait cost + the
cell's distance against move cost + the next cell's distance); it plays no part in distances.
Unit costs (1 everywhere) give exactly the BFS distances and the unguided rules' behaviour.

File format (`.guidance.npz`, documented in docs/guidance.md): a numpy npz with
  costs      float64 (H, W, 5) as above
  obstacles  uint8 (H, W), the map it was made for (1 = obstacle): a guidance file is refused
             for any other map
  meta       a JSON string: {"name", "kind" (unit, highways, learned, ...), free-form fields}
`Guidance.load(path, grid)` refuses, in one line naming the file and the problem, a file of the
wrong size or map, a negative, zero or NaN cost, and a layout whose forbidden moves cut a free
cell off from a cell it could reach on the map.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from mapf_fleet.files import atomic_write

from .actions import NUM_ACTIONS, move_targets

NONE = "none"  # the spelling of "no guidance" on every command line and ROS parameter
SUFFIX = ".guidance.npz"


class GuidanceError(ValueError):
    """A guidance graph that cannot be used (the message names the file and the problem)."""


@dataclass(frozen=True, eq=False)
class Guidance:
    """A guidance graph for one map. Build it with `Guidance.unit`, `Guidance.from_costs` or
    `Guidance.load`; `key` identifies its costs (distance tables are cached by it)."""

    obstacles: np.ndarray  # (H, W) bool
    costs: np.ndarray  # (H, W, 5) float64, inf where a move is forbidden or impossible
    meta: dict = field(default_factory=dict)
    key: str = ""

    # --- construction ----------------------------------------------------------------------
    @classmethod
    def from_costs(cls, grid, costs, meta: dict | None = None, source: str = "guidance") -> "Guidance":
        """Validated guidance for `grid` from (H, W, 5) costs (`source` names it in errors)."""
        blocked = np.asarray(grid) != 0
        costs = np.array(costs, dtype=np.float64)
        if costs.shape != (*blocked.shape, NUM_ACTIONS):
            raise GuidanceError(f"{source}: costs must have shape {(*blocked.shape, NUM_ACTIONS)} "
                                f"for this {blocked.shape[0]}x{blocked.shape[1]} map, got "
                                f"{costs.shape}")
        targets = move_targets(blocked).reshape(*blocked.shape, NUM_ACTIONS)
        valid = (targets >= 0) & ~blocked[..., None]
        used = costs[valid]
        if np.isnan(used).any():
            r, c, a = np.argwhere(valid & np.isnan(costs))[0]
            raise GuidanceError(f"{source}: cost of action {a} at cell ({r}, {c}) is NaN")
        if (used <= 0).any():
            r, c, a = np.argwhere(valid & (costs <= 0))[0]
            raise GuidanceError(f"{source}: cost of action {a} at cell ({r}, {c}) is "
                                f"{costs[r, c, a]:g}; costs must be > 0 (inf forbids a move)")
        if np.isinf(costs[..., 0][~blocked]).any():
            r, c = np.argwhere(~blocked & np.isinf(costs[..., 0]))[0]
            raise GuidanceError(f"{source}: the wait cost at cell ({r}, {c}) is inf; waiting "
                                f"must always be possible")
        costs = np.where(valid, costs, np.inf)
        guidance = cls(blocked, costs, dict(meta or {}), _key(blocked, costs))
        guidance._check_connected(source)
        costs.setflags(write=False)
        return guidance

    @classmethod
    def unit(cls, grid) -> "Guidance":
        """Cost 1 for every move and wait: distances are BFS steps (the unguided world)."""
        blocked = np.asarray(grid) != 0
        return cls.from_costs(blocked, np.ones((*blocked.shape, NUM_ACTIONS)), {"kind": "unit"})

    @classmethod
    def load(cls, path, grid) -> "Guidance":
        """The guidance file at `path` for `grid`; GuidanceError naming the file otherwise."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as data:
                missing = {"costs", "obstacles"} - set(data.files)
                if missing:
                    raise GuidanceError(f"{path}: not a guidance file (missing {sorted(missing)})")
                costs, obstacles = data["costs"], data["obstacles"]
                meta = json.loads(str(data["meta"])) if "meta" in data.files else {}
        except GuidanceError:
            raise
        except (OSError, ValueError, json.JSONDecodeError) as exc:
            raise GuidanceError(f"{path}: cannot read a guidance file ({exc})") from None
        blocked = np.asarray(grid) != 0
        if obstacles.shape != blocked.shape:
            raise GuidanceError(f"{path}: made for a {obstacles.shape[0]}x{obstacles.shape[1]} "
                                f"map, this map is {blocked.shape[0]}x{blocked.shape[1]}")
        if not np.array_equal(obstacles != 0, blocked):
            r, c = np.argwhere((obstacles != 0) != blocked)[0]
            raise GuidanceError(f"{path}: made for another map (cell ({r}, {c}) differs)")
        return cls.from_costs(blocked, costs, meta, source=str(path))

    def save(self, path) -> Path:
        """Write the guidance file (atomically: a reader never sees half a file)."""
        return atomic_write(path, lambda handle: np.savez_compressed(
            handle, costs=self.costs, obstacles=self.obstacles.astype(np.uint8),
            meta=np.array(json.dumps(self.meta))))

    # --- what the distance table reads ----------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        return self.obstacles.shape

    @property
    def is_unit(self) -> bool:
        """Every allowed move and wait costs 1 and no move is forbidden: BFS distances."""
        targets = move_targets(self.obstacles).reshape(*self.shape, NUM_ACTIONS)
        valid = (targets >= 0) & ~self.obstacles[..., None]
        return bool((self.costs[valid] == 1.0).all())

    def step_costs(self) -> np.ndarray:
        """(H*W, 5) float64 costs by flat cell (inf where forbidden or impossible)."""
        return self.costs.reshape(-1, NUM_ACTIONS)

    def reverse_graph(self) -> csr_matrix:
        """The graph whose shortest paths from a goal are the guided distances to it: an edge
        v -> u of cost c(u -> v) for every allowed move u -> v."""
        h, w = self.shape
        targets = move_targets(self.obstacles)
        costs = self.step_costs()
        src, act = np.nonzero((targets[:, 1:] >= 0) & np.isfinite(costs[:, 1:]))
        dst = targets[src, act + 1]
        graph = csr_matrix((costs[src, act + 1], (dst, src)), shape=(h * w, h * w))
        graph.sum_duplicates()
        return graph

    def _check_connected(self, source: str) -> None:
        """Forbidden moves must not cut a free cell off: within each region of the map every
        cell must still reach every other (strongly connected)."""
        targets = move_targets(self.obstacles).reshape(*self.shape, NUM_ACTIONS)
        moves = (targets[..., 1:] >= 0) & ~self.obstacles[..., None]
        if np.isfinite(self.costs[..., 1:][moves]).all():
            return  # nothing forbidden: the map's own regions
        graph = self.reverse_graph()
        free = ~self.obstacles.ravel()
        _, weak = connected_components(graph, directed=True, connection="weak")
        _, strong = connected_components(graph, directed=True, connection="strong")
        # a weak region split into several strong ones: some cell cannot get back
        for region in np.unique(weak[free]):
            cells = np.flatnonzero(free & (weak == region))
            if len(np.unique(strong[cells])) > 1:
                cell = int(cells[np.argmin(np.bincount(strong[cells])[strong[cells]])])
                r, c = divmod(cell, self.shape[1])
                raise GuidanceError(f"{source}: its one-way moves cut cell ({r}, {c}) off from "
                                    f"the rest of its region (every free cell must be able to "
                                    f"reach every cell it could reach on the map)")


def _key(blocked: np.ndarray, costs: np.ndarray) -> str:
    digest = hashlib.sha1(np.packbits(blocked).tobytes())
    digest.update(np.ascontiguousarray(costs).tobytes())
    return digest.hexdigest()[:16]


def load_guidance(value, grid) -> Guidance | None:
    """A `--guidance` value: None for "none" (or None / empty), else the file's guidance for
    `grid`."""
    if value is None or isinstance(value, Guidance):
        return value
    text = str(value).strip()
    if text in ("", NONE):
        return None
    return Guidance.load(text, grid)


def check_guidance_arg(value: str) -> str:
    """A `--guidance` value checked before anything starts: "none", or an existing readable
    guidance file (the map match is checked when the map is known)."""
    text = str(value).strip()
    if text in ("", NONE):
        return NONE
    path = Path(text)
    if not path.is_file():
        raise GuidanceError(f"--guidance: no such file: {text} (a guidance file, or 'none')")
    return str(path)


__all__ = ["Guidance", "GuidanceError", "NONE", "SUFFIX", "load_guidance", "check_guidance_arg"]
