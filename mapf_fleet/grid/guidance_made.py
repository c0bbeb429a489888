"""Where guidance graphs come from (numpy only): hand-made ones, a learned cost model, and the
`--guidance` value that names one.

- `highways(grid)`: one-way-leaning lanes in a crisscross (the League of Robot Runners' hand-made
  guidance): on even rows moving right is cheap and left dear, on odd rows the reverse; on even
  columns moving down is cheap, on odd columns up. Soft costs (`against` > 1), never forbidden,
  so every cell keeps every path and narrow corridors still serve both ways.
- `CostModel`: a small map-agnostic model of edge costs, cost(u -> v) = exp(theta . f(u, v)) with
  local features f (the crisscross lane agreement, how many free neighbours the cells have,
  corridors and dead ends, moving toward the map's centre). theta = 0 is unit costs (no guidance).
  Its parameters are learned by CMA-ES against lifelong throughput on a family of maps
  (`mapf-fleet guidance optimize`, GGO's recipe: Zhang et al., IJCAI 2024, who optimise a
  guidance policy over local patterns the same way); being a function of the local map, it gives
  guidance for maps it never saw.
- `CongestionFlow`: costs updated online from the robots' recent moves (traffic flow), no
  training: `--guidance congestion`.
- `GuidanceSource.parse(value)`: "none", "highways", "congestion", a guidance file
  (`*.guidance.npz`, one map), a cost model (`*.costmodel.json`, any map) or an online model
  (`*.online.json`, any map: costs from the map and recent traffic, `guidance_online`), parsed
  once where a value enters (the CLI, a ROS parameter); `source.for_map(grid)` gives the map's
  `Guidance` (None for "none").
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapf_fleet.files import atomic_write

from .actions import NUM_ACTIONS, move_targets
from .guidance import NONE, SUFFIX, Guidance, GuidanceError

HIGHWAYS = "highways"
MODEL_SUFFIX = ".costmodel.json"
# online learned guidance (`guidance_online`, which imports this module: named here for parse)
ONLINE = "online"
ONLINE_SUFFIX = ".online.json"
# the cost of moving against a highway lane (with it: 1); chosen by measurement
# (docs/results.md, "Continuous operation with guidance")
HIGHWAY_AGAINST = 2.0
# the model's log-costs are clipped to this range: costs stay within [e^-C, e^C]
LOG_COST_CLIP = 2.0

FEATURES = ("bias", "lane", "target_degree", "source_degree", "corridor", "dead_end",
            "to_centre", "turn_free")


def _lane_agreement(h: int, w: int) -> np.ndarray:
    """(H, W, 4) +1 where a move (up, down, left, right) follows its crisscross lane, -1 against."""
    rows = np.arange(h)[:, None]
    cols = np.arange(w)[None, :]
    right = np.where(rows % 2 == 0, 1.0, -1.0) * np.ones((1, w))
    down = np.where(cols % 2 == 0, 1.0, -1.0) * np.ones((h, 1))
    return np.stack([-down, down, -right, right], axis=-1)


def highways(grid, against: float = HIGHWAY_AGAINST) -> Guidance:
    """Crisscross highway guidance for `grid` (module docstring): cost 1 with the lane, `against`
    against it, waits 1."""
    blocked = np.asarray(grid) != 0
    h, w = blocked.shape
    costs = np.ones((h, w, NUM_ACTIONS))
    costs[..., 1:] = np.where(_lane_agreement(h, w) > 0, 1.0, float(against))
    return Guidance.from_costs(blocked, costs, {"kind": HIGHWAYS, "against": float(against)},
                               source="highways")


def features(grid) -> np.ndarray:
    """(H, W, 4, F) the `FEATURES` of every move (up, down, left, right) from every cell."""
    blocked = np.asarray(grid) != 0
    h, w = blocked.shape
    targets = move_targets(blocked)[:, 1:]  # (H*W, 4)
    padded = np.pad(~blocked, 1)
    degree = (padded[:-2, 1:-1].astype(float) + padded[2:, 1:-1] + padded[1:-1, :-2]
              + padded[1:-1, 2:]).ravel()
    valid = targets >= 0
    t = np.where(valid, targets, 0)
    target_degree = np.where(valid, degree[t], 0.0)
    source_degree = np.repeat(degree[:, None], 4, axis=1)
    rows, cols = np.divmod(np.arange(h * w), w)
    centre = np.array([(h - 1) / 2, (w - 1) / 2])
    here = np.abs(rows - centre[0]) + np.abs(cols - centre[1])
    there = np.abs(rows[t] - centre[0]) + np.abs(cols[t] - centre[1])
    # a move whose target lets a robot turn (a free cell beside the way on): crossings
    turn = np.where(valid, (target_degree >= 3).astype(float), 0.0)
    f = np.stack([
        np.ones((h * w, 4)),
        _lane_agreement(h, w).reshape(h * w, 4),
        target_degree / 4.0,
        source_degree / 4.0,
        (target_degree == 2).astype(float),
        (target_degree == 1).astype(float),
        np.sign(here[:, None] - there),
        turn,
    ], axis=-1)
    return np.where(valid[..., None], f, 0.0).reshape(h, w, 4, len(FEATURES))


@dataclass
class CostModel:
    """cost(u -> v) = exp(clip(theta . features(u, v))), waits exp(wait); `theta` over
    `FEATURES`. `meta`: how it was made (the card's facts)."""

    theta: np.ndarray
    wait: float = 0.0
    meta: dict = field(default_factory=dict)

    @classmethod
    def zeros(cls) -> "CostModel":
        return cls(np.zeros(len(FEATURES)))

    @classmethod
    def from_vector(cls, x, meta: dict | None = None) -> "CostModel":
        """The model of a flat parameter vector (theta, then the wait's log-cost)."""
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (len(FEATURES) + 1,):
            raise ValueError(f"a cost model has {len(FEATURES) + 1} parameters, got {x.shape}")
        return cls(x[:-1].copy(), float(x[-1]), dict(meta or {}))

    def vector(self) -> np.ndarray:
        return np.append(self.theta, self.wait)

    def guidance(self, grid) -> Guidance:
        blocked = np.asarray(grid) != 0
        logc = np.clip(features(blocked) @ self.theta, -LOG_COST_CLIP, LOG_COST_CLIP)
        costs = np.empty((*blocked.shape, NUM_ACTIONS))
        costs[..., 0] = np.exp(np.clip(self.wait, -LOG_COST_CLIP, LOG_COST_CLIP))
        costs[..., 1:] = np.exp(logc)
        return Guidance.from_costs(blocked, costs, {"kind": "costmodel", **self.meta},
                                   source="cost model")

    def save(self, path) -> Path:
        data = {"features": list(FEATURES), "theta": self.theta.tolist(), "wait": self.wait,
                "meta": self.meta}
        return atomic_write(path, (json.dumps(data, indent=1) + "\n").encode())

    @classmethod
    def load(cls, path) -> "CostModel":
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise GuidanceError(f"{path}: cannot read a cost model ({exc})") from None
        if not isinstance(data, dict) or data.get("features") != list(FEATURES):
            raise GuidanceError(f"{path}: field 'features' must be {list(FEATURES)}")
        theta = np.asarray(data.get("theta"), dtype=np.float64)
        if theta.shape != (len(FEATURES),) or not np.isfinite(theta).all():
            raise GuidanceError(f"{path}: field 'theta' must be {len(FEATURES)} finite numbers")
        wait = data.get("wait", 0.0)
        if not isinstance(wait, (int, float)) or not np.isfinite(wait):
            raise GuidanceError(f"{path}: field 'wait' must be a finite number, got {wait!r}")
        return cls(theta, float(wait), dict(data.get("meta") or {}))


@dataclass(frozen=True)
class GuidanceSource:
    """What a `--guidance` value names: `kind` none, highways, congestion, file, model or online;
    `path` for the last three. Parse once with `GuidanceSource.parse`; `for_map(grid)` per map."""

    kind: str
    path: str = ""
    # in memory: a CostModel (kind model) or a guidance_online.OnlineModel (kind online)
    model: "CostModel | None" = field(default=None, compare=False, hash=False)

    @classmethod
    def parse(cls, value) -> "GuidanceSource":
        if isinstance(value, GuidanceSource):
            return value
        text = "" if value is None else str(value).strip()
        if text in ("", NONE):
            return cls(NONE)
        if text in (HIGHWAYS, CONGESTION):
            return cls(text)
        path = Path(text)
        if not path.is_file():
            raise GuidanceError(f"guidance must be 'none', 'highways', 'congestion', a guidance "
                                f"file (*{SUFFIX}), a cost model (*{MODEL_SUFFIX}) or an online "
                                f"model (*{ONLINE_SUFFIX}); no such file: {text}")
        if text.endswith(MODEL_SUFFIX):
            # read once (refused here, before anything starts), not again for every map
            return cls("model", str(path), model=CostModel.load(path))
        if text.endswith(ONLINE_SUFFIX):
            from .guidance_online import OnlineModel

            return cls(ONLINE, str(path), model=OnlineModel.load(path))
        return cls("file", str(path))

    def __str__(self) -> str:
        return self.path or self.kind

    @property
    def online(self) -> bool:
        """The graph changes as the fleet moves (`CongestionFlow`, `OnlineFlow`): the run
        updates it."""
        return self.kind in (CONGESTION, ONLINE)

    def flow(self, grid) -> "CongestionFlow | None":
        if self.kind == ONLINE:
            from .guidance_online import OnlineFlow, OnlineModel

            return OnlineFlow(grid, self.model or OnlineModel.load(self.path))
        return CongestionFlow(grid) if self.online else None

    @property
    def label(self) -> str:
        """Short name for tables: none, highways, or the file's stem."""
        if self.model is not None and not self.path:
            return "learned"
        if not self.path:
            return self.kind
        name = Path(self.path).name
        for suffix in (MODEL_SUFFIX, ONLINE_SUFFIX, SUFFIX):
            name = name.removesuffix(suffix)
        return name

    def for_map(self, grid) -> Guidance | None:
        if self.kind == NONE:
            return None
        if self.kind == HIGHWAYS:
            return highways(grid)
        if self.kind == CONGESTION:
            return None  # unit costs until the first update (`CongestionFlow`)
        if self.kind == "model":
            return (self.model or CostModel.load(self.path)).guidance(grid)
        if self.kind == ONLINE:  # its static part until the first update (`OnlineFlow`)
            from .guidance_online import OnlineModel

            return (self.model or OnlineModel.load(self.path)).guidance(grid)
        return Guidance.load(self.path, grid)



# --- congestion-aware guidance, updated online (no training) -----------------------------------
CONGESTION = "congestion"
# contraflow weight, decay per tick and ticks between updates of the congestion costs; chosen by
# measurement (docs/results.md, "Continuous operation with guidance")
CONGESTION_BETA = 0.5
CONGESTION_DECAY = 0.9
CONGESTION_PERIOD = 8


class CongestionFlow:
    """Traffic-flow guidance from where the robots are and are heading (Chen et al., AAAI 2024,
    the hand-made counterpart of learned guidance): a decayed count of the moves robots made along
    each directed edge; moving against recent traffic costs 1 + beta x (the flow the other way) /
    (1 + the flow this way), so opposite streams keep apart. `step(before, after)` after each
    tick: the new graph every `period` ticks, None between updates."""

    def __init__(self, grid, beta: float = CONGESTION_BETA, decay: float = CONGESTION_DECAY,
                 period: int = CONGESTION_PERIOD):
        self.blocked = np.asarray(grid) != 0
        h, w = self.blocked.shape
        self.width = w
        self.flow = np.zeros((h * w, NUM_ACTIONS))  # decayed moves out of a cell per action
        self.beta, self.decay, self.period = float(beta), float(decay), int(period)
        self.ticks = 0
        self._opposite = np.array([0, 2, 1, 4, 3])  # up <-> down, left <-> right
        targets = move_targets(self.blocked)
        self._targets = targets

    def step(self, before, after) -> "Guidance | None":
        """Count one tick's moves (`before` -> `after` cells); the new graph when a period ends."""
        self.observe(before, after)
        return self.guidance()

    def observe(self, before, after) -> None:
        before = np.asarray(before, dtype=np.int64)
        after = np.asarray(after, dtype=np.int64)
        self.flow *= self.decay
        delta = after - before
        moved = np.abs(delta).sum(axis=1) == 1
        if moved.any():
            from .actions import actions_between

            actions = actions_between(before[moved], after[moved])
            cells = before[moved, 0] * self.width + before[moved, 1]
            np.add.at(self.flow, (cells, actions), 1.0)
        self.ticks += 1

    def guidance(self) -> "Guidance | None":
        if self.ticks % self.period:
            return None
        h, w = self.blocked.shape
        t = self._targets
        valid = t >= 0
        # the flow the other way over each edge u -> v: moves out of v with the opposite action
        back = np.where(valid, self.flow[np.where(valid, t, 0), self._opposite[None, :]], 0.0)
        costs = 1.0 + self.beta * back / (1.0 + self.flow)
        costs[:, 0] = 1.0
        return Guidance.from_costs(self.blocked, costs.reshape(h, w, NUM_ACTIONS),
                                   {"kind": CONGESTION}, source="congestion")


class FlowFollower:
    """Online guidance (`GuidanceSource.online`) followed from a fleet's states as the run that
    steps it has it (`fleet.run.FleetRun.advance`: the flow observes each tick's moves, and a
    decision at tick t reads the graph of the moves before t). A fleet's policy processes see
    every state (every robot's cell at every tick, in order) but not the simulator's graph: each
    follows the same flow over the same cells, so every process and the rule read one graph
    (`models.exchange.PolicyExchange`).

    `follow(episode, tick, cells)` for each state, in order; `at(tick)` the graph of a decision
    at `tick` (None: BFS steps). It can follow a run only from its first tick: a state missed
    (a tick skipped) or a first state after tick 0 (a process that joined late) leaves it
    `broken` (why, in words), and its graph stays what it was (the robots' observations then
    differ from the rule's graph; every move is still the rule's)."""

    KEEP = 8  # graphs of the last ticks (a decision runs a tick or two behind the newest state)

    def __init__(self, source: GuidanceSource, grid):
        import threading

        self.source, self.grid = source, np.asarray(grid) != 0
        self._lock = threading.Lock()
        self._reset(None)

    def _reset(self, episode) -> None:
        self.episode = episode
        self.flow = self.source.flow(self.grid)
        self.graph = self.source.for_map(self.grid)
        self.tick = None
        self.cells = None
        self.broken = ""
        self._graphs: dict[int, Guidance | None] = {}

    def follow(self, episode, tick: int, cells) -> None:
        cells = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
        tick = int(tick)
        with self._lock:
            if episode != self.episode:
                self._reset(episode)
            if self.tick is None:
                if tick != 0:
                    self.broken = f"joined at tick {tick}: the moves before it are unknown"
            elif tick <= self.tick:
                return  # the same state again
            elif tick != self.tick + 1:
                if not self.broken:
                    self.broken = f"states of ticks {self.tick + 1}..{tick - 1} were missed"
            elif not self.broken:
                graph = self.flow.step(self.cells, cells)
                if graph is not None:
                    self.graph = graph
            self.tick, self.cells = tick, cells
            self._graphs[tick] = self.graph
            for old in [t for t in self._graphs if t <= tick - self.KEEP]:
                del self._graphs[old]

    def at(self, tick: int) -> "Guidance | None":
        """The graph a decision at `tick` reads (the newest one followed if `tick` was not)."""
        with self._lock:
            return self._graphs.get(int(tick), self.graph)


__all__ = ["highways", "features", "CostModel", "GuidanceSource", "CongestionFlow", "FEATURES",
           "HIGHWAYS", "CONGESTION", "MODEL_SUFFIX", "HIGHWAY_AGAINST", "FlowFollower"]
