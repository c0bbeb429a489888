"""Synthetic fleets for tests and benchmarks: observations consistent with positions, no grid."""

from __future__ import annotations

import numpy as np
import torch


def random_positions(rng: np.random.Generator, num_agents: int, side: int) -> np.ndarray:
    """num_agents distinct cells of a side x side map, (N, 2) int64."""
    cells = rng.choice(side * side, size=num_agents, replace=False)
    return np.stack([cells // side, cells % side], axis=1).astype(np.int64)


def synthetic_obs(rng: np.random.Generator, positions: np.ndarray, radius: int = 4,
                  side: int | None = None) -> np.ndarray:
    """(N, 6, 2r+1, 2r+1) float32: channel 0 = other agents inside the FOV (consistent with
    positions), channel 1 random obstacles (never under an agent), 2..5 random heuristic bits."""
    n = len(positions)
    fov = 2 * radius + 1
    obs = np.zeros((n, 6, fov, fov), dtype=np.float32)
    obs[:, 1] = rng.random((n, fov, fov)) < 0.25
    obs[:, 2:] = rng.random((n, 4, fov, fov)) < 0.4
    for i in range(n):
        delta = positions - positions[i]
        inside = (np.abs(delta) <= radius).all(1)
        inside[i] = False
        cells = delta[inside] + radius
        obs[i, 0, cells[:, 0], cells[:, 1]] = 1.0
        obs[i, 1, cells[:, 0], cells[:, 1]] = 0.0
        obs[i, 1, radius, radius] = 0.0
    return obs


def make_sensitive(net: torch.nn.Module, seed: int, weight_scale: float = 1.2,
                   head_scale: float = 0.5, agent_channel_scale: float = 3.0) -> torch.nn.Module:
    """Re-initialise with larger weights so greedy actions react to single agents.

    With PyTorch's default init a freshly built network hardly ever changes its greedy action
    when one neighbour is erased, so DCC would never communicate and the tests would not
    exercise the communication path.
    """
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            if p.dim() > 1:
                fan_in = p[0].numel()
                p.copy_(torch.randn(p.shape, generator=gen) * (weight_scale / fan_in**0.5))
            else:
                p.copy_(torch.randn(p.shape, generator=gen) * 0.1)
        # Neighbours (observation channel 0) weigh more, so erasing one often flips an action.
        net.obs_encoder[0].weight[:, 0] *= agent_channel_scale
        for p in net.head.parameters():
            p.mul_(head_scale)
    return net
