"""Pieces shared by DHC and DCC: the step result, the dueling head, input checking."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from mapf_fleet.grid.actions import NUM_ACTIONS

from .config import ModelConfig


@dataclass
class StepOutput:
    """Result of one batched step.

    q: (B, N, 5) Q-values (zero for padded agents).
    hidden: (B, N, H) the hidden state to carry to the next step: the post-communication
        hidden (zero for padded agents), as in both reference implementations.
    comm_mask: (B, N, N) bool, self excluded. DHC: [b, i, j] = j is one of i's partners (i attends
        to j). DCC: [b, i, j] = i requests from j (j's erasure changed i's greedy action), the
        orientation of the DCC reference's comm_mask.
    partners: DHC only: (B, N, k) partner indices, -1 for none.
    """

    q: torch.Tensor
    hidden: torch.Tensor
    comm_mask: torch.Tensor
    partners: torch.Tensor | None = None

    @property
    def actions(self) -> torch.Tensor:
        """Greedy actions (B, N), lowest action index on exact ties (torch.argmax)."""
        return self.q.argmax(-1)


class DuelingHead(nn.Module):
    """Q = V + A - mean(A) (Wang et al. 2016); attribute names follow the reference code."""

    def __init__(self, hidden_dim: int):
        super().__init__()
        self.adv = nn.Linear(hidden_dim, NUM_ACTIONS)
        self.state = nn.Linear(hidden_dim, 1)

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        adv = self.adv(hidden)
        return self.state(hidden) + adv - adv.mean(-1, keepdim=True)


def padded_rows(rows: int) -> int:
    """`rows` rounded up to one of 8 sizes per power of two (at most 1/8 more rows; exact below
    16). Inference batches whose size changes every step (DCC's variants) then take a bounded
    set of shapes: oneDNN compiles and keeps a kernel per input shape, so with a new shape
    nearly every tick a fleet's policy process kept growing (docs/results.md, "The ROS
    fleet at 128 / 256 / 512 / 1,024 robots")."""
    step = 1 << max(0, int(rows).bit_length() - 4)
    return -(-int(rows) // step) * step


def pad_rows(rows: int, *tensors: torch.Tensor) -> tuple:
    """Each tensor with its first dimension padded to `rows` (zeros; integer tensors with -1),
    for rows computed independently of one another (no batch statistics)."""
    out = []
    for t in tensors:
        missing = rows - len(t)
        if missing > 0:
            fill = -1 if not t.is_floating_point() else 0
            t = torch.cat([t, t.new_full((missing, *t.shape[1:]), fill)])
        out.append(t)
    return tuple(out)


def module_device(module: nn.Module) -> torch.device:
    return next(module.parameters()).device


def as_float(x, name: str, device: torch.device) -> torch.Tensor:
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(x)
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name}: expected a tensor or numpy array, got {type(x).__name__}")
    return x.to(device=device, dtype=torch.float32)


def as_long(x, name: str, device: torch.device) -> torch.Tensor:
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(np.ascontiguousarray(x))
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name}: expected a tensor or numpy array, got {type(x).__name__}")
    if x.is_floating_point():
        raise TypeError(f"{name}: expected integers, got dtype {x.dtype}")
    return x.to(device=device, dtype=torch.long)


def check_batch_inputs(
    config: ModelConfig,
    obs: torch.Tensor,
    positions: torch.Tensor,
    hidden: torch.Tensor | None,
    agent_mask: torch.Tensor | None,
) -> tuple[int, int]:
    """Raise a ValueError naming the argument whose shape is wrong; return (B, N)."""
    if obs.dim() != 5 or tuple(obs.shape[2:]) != config.obs_shape:
        raise ValueError(f"obs: expected (B, N, {', '.join(map(str, config.obs_shape))}), "
                         f"got {tuple(obs.shape)}")
    batch, num_agents = obs.shape[:2]
    if tuple(positions.shape) != (batch, num_agents, 2):
        raise ValueError(f"positions: expected {(batch, num_agents, 2)}, "
                         f"got {tuple(positions.shape)}")
    if hidden is not None and tuple(hidden.shape) != (batch, num_agents, config.hidden_dim):
        raise ValueError(f"hidden: expected {(batch, num_agents, config.hidden_dim)}, "
                         f"got {tuple(hidden.shape)}")
    if agent_mask is not None and tuple(agent_mask.shape) != (batch, num_agents):
        raise ValueError(f"agent_mask: expected {(batch, num_agents)}, "
                         f"got {tuple(agent_mask.shape)}")
    return batch, num_agents
