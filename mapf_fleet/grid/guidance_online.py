"""Online learned guidance (numpy only): edge costs from the map and from recent traffic,
recomputed every few ticks as the fleet moves (Online GGO, Zhang et al., AAAI 2025: a small model
of local traffic statistics trained by CMA-ES against throughput, no gradients).

`OnlineModel` is a log-linear model over two groups of per-move features:

    cost(u -> v) = exp(clip(theta . f(u, v) + phi . g(u, v), -C, C)),  wait cost exp(wait)

f: the static `FEATURES` of the cost model (`guidance_made.features`: lane agreement, free
neighbours, corridors, dead ends, toward the centre, crossings); g: the `TRAFFIC` statistics of
the move, decayed counts (by `decay` per tick) of what the robots did lately:

- contraflow: log(1 + beta * back / (1 + same)), beta = `CONGESTION_BETA`: exactly the log-cost
  of `CongestionFlow`, so phi = (1, 0, ...) with theta = 0 *is* `--guidance congestion`;
- flow_same / flow_back: log(1 + moves along u -> v) / log(1 + moves along v -> u);
- wait_target: log(1 + robots that stayed put on v), queues ahead;
- through_target: log(1 + moves out of v), crossing traffic at v.

With no traffic every g is 0 and the costs are the static part alone (a `CostModel` with the same
theta and wait). The hand-made graphs are points of the model: `OnlineModel.preset("highways")`
gives exactly the crisscross highways, `"congestion"` the congestion costs, `"both"` the two
together; CMA-ES starts from one of them (`mapf-fleet guidance optimize --model online`).

Being a function of the local map and the local traffic, the model gives guidance for any map.
`OnlineFlow` steps it inside a run: the same plumbing as `CongestionFlow` (whose decayed move
counts it reuses; `fleet.run.FleetRun` calls `observe(before, after)` after every tick and takes
`guidance()` every `period` ticks).

File format (`NAME.online.json`, docs/guidance.md): a JSON object
  kind             "online"
  static_features  the names of `FEATURES`, in order
  traffic_features the names of `TRAFFIC`, in order
  theta, phi       finite numbers, one per feature of each group
  wait             the wait's log-cost (finite)
  decay            the counts' decay per tick, in (0, 1]
  period           ticks between cost updates, an integer >= 1
  meta             how it was made (free-form; the card's facts)
`OnlineModel.load` refuses anything else in one line naming the file, the field and the value.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapf_fleet.files import atomic_write

from .actions import NUM_ACTIONS
from .guidance import Guidance, GuidanceError
from .guidance_made import (CONGESTION_BETA, CONGESTION_DECAY, CONGESTION_PERIOD, FEATURES,
                            HIGHWAY_AGAINST, LOG_COST_CLIP, ONLINE, ONLINE_SUFFIX, CongestionFlow,
                            features)
TRAFFIC = ("contraflow", "flow_same", "flow_back", "wait_target", "through_target")
PRESETS = ("none", "highways", "congestion", "both")


@dataclass
class OnlineModel:
    """The online cost model (module docstring): `theta` over `FEATURES`, `phi` over `TRAFFIC`,
    the wait's log-cost, the counts' `decay` per tick and the update `period` in ticks."""

    theta: np.ndarray
    phi: np.ndarray
    wait: float = 0.0
    decay: float = CONGESTION_DECAY
    period: int = CONGESTION_PERIOD
    meta: dict = field(default_factory=dict)

    @classmethod
    def size(cls) -> int:
        """How many parameters CMA-ES searches: theta, phi, the wait."""
        return len(FEATURES) + len(TRAFFIC) + 1

    @classmethod
    def preset(cls, name: str) -> "OnlineModel":
        """The hand-made graphs as points of the model: none (unit costs), highways (cost 1
        with a lane, `HIGHWAY_AGAINST` against it), congestion (`CongestionFlow`'s costs) or
        both (highways' costs times congestion's)."""
        if name not in PRESETS:
            raise ValueError(f"online model preset must be one of {PRESETS}, got {name!r}")
        theta, phi = np.zeros(len(FEATURES)), np.zeros(len(TRAFFIC))
        if name in ("highways", "both"):
            # log cost = ln(a)/2 * (1 - lane): 0 with the lane (+1), ln(a) against it (-1)
            half = np.log(HIGHWAY_AGAINST) / 2
            theta[FEATURES.index("bias")] = half
            theta[FEATURES.index("lane")] = -half
        if name in ("congestion", "both"):
            phi[TRAFFIC.index("contraflow")] = 1.0
        return cls(theta, phi, meta={"init": name})

    @classmethod
    def from_vector(cls, x, meta: dict | None = None, decay: float = CONGESTION_DECAY,
                    period: int = CONGESTION_PERIOD) -> "OnlineModel":
        """The model of a flat parameter vector (theta, phi, then the wait's log-cost)."""
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (cls.size(),):
            raise ValueError(f"an online model has {cls.size()} parameters, got {x.shape}")
        k = len(FEATURES)
        return cls(x[:k].copy(), x[k:-1].copy(), float(x[-1]), decay, period, dict(meta or {}))

    def vector(self) -> np.ndarray:
        return np.concatenate([self.theta, self.phi, [self.wait]])

    # --- costs -------------------------------------------------------------------------------
    def static_log_costs(self, grid) -> np.ndarray:
        """(H*W, 4) theta . f of every move (up, down, left, right) from every cell."""
        blocked = np.asarray(grid) != 0
        f = features(blocked)
        return (f @ self.theta).reshape(-1, 4)

    def costs(self, grid, static_log: np.ndarray, traffic: np.ndarray | None) -> Guidance:
        """The validated graph of `grid` from its static log-costs (`static_log_costs`) and the
        (H*W, 4, len(TRAFFIC)) traffic features (None: no traffic)."""
        blocked = np.asarray(grid) != 0
        logc = static_log if traffic is None else static_log + traffic @ self.phi
        costs = np.empty((blocked.size, NUM_ACTIONS))
        costs[:, 0] = np.exp(np.clip(self.wait, -LOG_COST_CLIP, LOG_COST_CLIP))
        costs[:, 1:] = np.exp(np.clip(logc, -LOG_COST_CLIP, LOG_COST_CLIP))
        return Guidance.from_costs(blocked, costs.reshape(*blocked.shape, NUM_ACTIONS),
                                   {"kind": ONLINE, **self.meta}, source="online model")

    def guidance(self, grid) -> Guidance:
        """The graph with no traffic yet: the static part alone (a run's first ticks)."""
        return self.costs(grid, self.static_log_costs(grid), None)

    # --- the file ----------------------------------------------------------------------------
    def save(self, path) -> Path:
        data = {"kind": ONLINE, "static_features": list(FEATURES),
                "traffic_features": list(TRAFFIC), "theta": self.theta.tolist(),
                "phi": self.phi.tolist(), "wait": self.wait, "decay": self.decay,
                "period": self.period, "meta": self.meta}
        return atomic_write(path, (json.dumps(data, indent=1) + "\n").encode())

    @classmethod
    def load(cls, path) -> "OnlineModel":
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise GuidanceError(f"{path}: cannot read an online model ({exc})") from None
        if not isinstance(data, dict):
            raise GuidanceError(f"{path}: an online model is a JSON object, got "
                                f"{type(data).__name__}")

        def refuse(name, what):
            raise GuidanceError(f"{path}: field '{name}' must be {what}, got "
                                f"{data.get(name)!r:.80}")

        if data.get("kind") != ONLINE:
            refuse("kind", f"{ONLINE!r}")
        for name, names in (("static_features", FEATURES), ("traffic_features", TRAFFIC)):
            if data.get(name) != list(names):
                refuse(name, list(names))
        vectors = {}
        for name, n in (("theta", len(FEATURES)), ("phi", len(TRAFFIC))):
            value = data.get(name)
            ok = (isinstance(value, list) and len(value) == n
                  and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value))
            if not ok or not np.isfinite(np.asarray(value, dtype=np.float64)).all():
                refuse(name, f"{n} finite numbers")
            vectors[name] = np.asarray(value, dtype=np.float64)
        wait = data.get("wait", 0.0)
        if not _finite_number(wait):
            refuse("wait", "a finite number")
        decay = data.get("decay")
        if not _finite_number(decay) or not 0.0 < decay <= 1.0:
            refuse("decay", "a number in (0, 1]")
        period = data.get("period")
        if not isinstance(period, int) or isinstance(period, bool) or period < 1:
            refuse("period", "an integer >= 1")
        meta = data.get("meta") or {}
        if not isinstance(meta, dict):
            refuse("meta", "a JSON object")
        return cls(vectors["theta"], vectors["phi"], float(wait), float(decay), period,
                   dict(meta))


def _finite_number(value) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and bool(np.isfinite(value)))


class OnlineFlow(CongestionFlow):
    """Steps an `OnlineModel` inside a run: `CongestionFlow`'s decayed move counts (and, in its
    unused wait column, the decayed count of robots that stayed put), turned into the model's
    costs every `period` ticks. `observe(before, after)` after each tick; `guidance()` gives the
    new graph on an update tick, None between."""

    def __init__(self, grid, model: OnlineModel):
        super().__init__(grid, beta=CONGESTION_BETA, decay=model.decay, period=model.period)
        self.model = model
        self._static = model.static_log_costs(self.blocked)

    def observe(self, before, after) -> None:
        super().observe(before, after)  # decays every column, counts the moves
        before = np.asarray(before, dtype=np.int64)
        stayed = (np.asarray(after, dtype=np.int64) == before).all(axis=1)
        if stayed.any():
            cells = before[stayed, 0] * self.width + before[stayed, 1]
            np.add.at(self.flow[:, 0], cells, 1.0)

    def traffic(self) -> np.ndarray:
        """(H*W, 4, len(TRAFFIC)) the `TRAFFIC` features of every move from every cell (0 for
        moves off the map or into obstacles)."""
        t = self._targets[:, 1:]
        valid = t >= 0
        v = np.where(valid, t, 0)
        same = self.flow[:, 1:]
        back = self.flow[v, self._opposite[None, 1:]]
        g = np.stack([
            np.log1p(self.beta * back / (1.0 + same)),
            np.log1p(same),
            np.log1p(back),
            np.log1p(self.flow[v, 0]),
            np.log1p(self.flow[v, 1:].sum(axis=-1)),
        ], axis=-1)
        return np.where(valid[..., None], g, 0.0)

    def guidance(self) -> "Guidance | None":
        if self.ticks % self.period:
            return None
        return self.model.costs(self.blocked, self._static, self.traffic())


__all__ = ["OnlineModel", "OnlineFlow", "ONLINE", "ONLINE_SUFFIX", "TRAFFIC", "PRESETS"]
