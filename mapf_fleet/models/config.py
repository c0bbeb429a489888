"""Network sizes for DHC and DCC (validated on construction) and the named presets.

`paper` reproduces the sizes of the reference implementations (DHC about 2.05 M parameters,
DCC about 1.98 M); `small` is meant for training on a 2-core CPU.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping

from mapf_fleet.grid.observation import OBSERVATIONS, observation_channels

ALGORITHMS = ("dhc", "dcc")
PRESETS = ("paper", "small")
# Observation channels of the paper (docs/architecture.md): other agents, obstacles, 4 heuristic
# directions; `ModelConfig.observation` "cost_to_go" adds a 7th (`ModelConfig.obs_shape`).
OBS_CHANNELS = observation_channels("paper")
# DHC squeezes its residual trunk to 16 channels before the GRU (reference code).
DHC_SQUEEZE_CHANNELS = 16


@dataclass(frozen=True)
class ModelConfig:
    """Sizes of one DHC or DCC network.

    conv_channels: DHC: one entry, the width of the stem conv and of the 3 residual blocks.
        DCC: four entries, the widths of the four valid 3x3 convs (the last is the latent size).
    hidden_dim: GRU hidden size (the vector exchanged between robots).
    num_heads, head_dim: attention heads and per-head width of the communication block.
    comm_rounds: DHC only: rounds of the shared attention + GRU update (DCC always has a
        request layer and a reply layer).
    max_partners: DHC only: how many nearest FOV neighbours an agent attends to (besides itself).
    pos_embed_dim: DCC only: width of the relative-position embedding joined to keys and values.
    attend_self: DCC only: whether a receiver's attention includes its own message (at offset
        (0, 0)) besides its senders'. The DCC reference attends over the senders only (False);
        this project's default is True (receivers attend over self + senders).
    obs_radius: r; the field of view is (2r+1) x (2r+1).
    observation: what the network reads, one of `grid.env.OBSERVATIONS`: "paper" (the paper's six
        channels) or "cost_to_go" (those plus the normalised cost-to-go channel,
        `grid.env.cost_to_go_channel`). Checkpoints without the field are "paper".
    """

    algo: str = "dhc"
    conv_channels: tuple[int, ...] = (128,)
    hidden_dim: int = 256
    num_heads: int = 2
    head_dim: int = 64
    comm_rounds: int = 2
    max_partners: int = 2
    pos_embed_dim: int = 16
    attend_self: bool = True
    obs_radius: int = 4
    observation: str = "paper"

    def __post_init__(self) -> None:
        # Accept lists (e.g. from YAML or a checkpoint) but store a tuple so the config is hashable.
        object.__setattr__(self, "conv_channels", tuple(self.conv_channels))
        if self.algo not in ALGORITHMS:
            raise ValueError(f"ModelConfig.algo: expected one of {ALGORITHMS}, got {self.algo!r}")
        expected_convs = 1 if self.algo == "dhc" else 4
        if len(self.conv_channels) != expected_convs or not all(
            _is_positive_int(c) for c in self.conv_channels
        ):
            raise ValueError(
                f"ModelConfig.conv_channels: {self.algo} needs {expected_convs} positive int(s), "
                f"got {self.conv_channels!r}"
            )
        for name in ("hidden_dim", "num_heads", "head_dim", "comm_rounds", "pos_embed_dim"):
            value = getattr(self, name)
            if not _is_positive_int(value):
                raise ValueError(f"ModelConfig.{name}: expected a positive int, got {value!r}")
        if not _is_positive_int(self.max_partners):
            raise ValueError(
                f"ModelConfig.max_partners: expected a positive int, got {self.max_partners!r}"
            )
        if not isinstance(self.attend_self, bool):
            raise ValueError(f"ModelConfig.attend_self: expected a bool, got {self.attend_self!r}")
        # DCC's four valid 3x3 convs shrink the FOV by 8 cells; DHC's stem conv by 2.
        min_radius = 4 if self.algo == "dcc" else 1
        if not _is_positive_int(self.obs_radius) or self.obs_radius < min_radius:
            raise ValueError(
                f"ModelConfig.obs_radius: {self.algo} needs an int >= {min_radius}, "
                f"got {self.obs_radius!r}"
            )
        if self.observation not in OBSERVATIONS:
            raise ValueError(
                f"ModelConfig.observation: expected one of {OBSERVATIONS}, got {self.observation!r}"
            )

    @property
    def fov(self) -> int:
        return 2 * self.obs_radius + 1

    @property
    def obs_shape(self) -> tuple[int, int, int]:
        return (observation_channels(self.observation), self.fov, self.fov)

    def to_dict(self) -> dict[str, Any]:
        """Plain types only (lists, ints, str, bool), as stored in checkpoints."""
        data = dataclasses.asdict(self)
        data["conv_channels"] = list(self.conv_channels)
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "ModelConfig":
        if not isinstance(data, Mapping):
            raise ValueError(f"ModelConfig: expected a mapping, got {type(data).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"ModelConfig: unknown field(s) {unknown}; known: {sorted(known)}")
        return cls(**dict(data))

    @classmethod
    def preset(cls, algo: str, name: str = "paper", **overrides: Any) -> "ModelConfig":
        """`paper` (default) or `small` sizes for `algo`; keyword overrides win."""
        key = (algo, name)
        if key not in _PRESETS:
            raise ValueError(
                f"ModelConfig.preset: unknown (algo, preset) {key}; "
                f"algos {ALGORITHMS}, presets {PRESETS}"
            )
        return cls(**{**_PRESETS[key], **overrides})


def _is_positive_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value > 0


_PRESETS: dict[tuple[str, str], dict[str, Any]] = {
    # Reference DHC: 128-channel trunk, GRU 256, 2 rounds of 2 heads x 64, 2 nearest partners.
    ("dhc", "paper"): dict(
        algo="dhc", conv_channels=(128,), hidden_dim=256, num_heads=2, head_dim=64,
        comm_rounds=2, max_partners=2,
    ),
    ("dhc", "small"): dict(
        algo="dhc", conv_channels=(32,), hidden_dim=64, num_heads=2, head_dim=16,
        comm_rounds=2, max_partners=2,
    ),
    # Reference DCC: convs 6-64-128-192-256, GRU(261, 256), request/reply layers 4 heads x 32.
    ("dcc", "paper"): dict(
        algo="dcc", conv_channels=(64, 128, 192, 256), hidden_dim=256, num_heads=4, head_dim=32,
        pos_embed_dim=16,
    ),
    ("dcc", "small"): dict(
        algo="dcc", conv_channels=(16, 32, 48, 64), hidden_dim=64, num_heads=4, head_dim=8,
        pos_embed_dim=8,
    ),
}


def paper_config(algo: str) -> ModelConfig:
    return ModelConfig.preset(algo, "paper")


def small_config(algo: str) -> ModelConfig:
    return ModelConfig.preset(algo, "small")
