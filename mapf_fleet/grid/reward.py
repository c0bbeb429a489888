"""The cooperative reward of the paper (Eq. 2) over FOV neighbours."""

from __future__ import annotations

import dataclasses

import numpy as np


def fov_neighbours(positions, radius: int = 4) -> np.ndarray:
    """bool (N, N): [i, j] is True when j != i stands in i's FOV (|dr| <= r and |dc| <= r)."""
    positions = np.asarray(positions, dtype=np.int64)
    if positions.ndim != 2 or positions.shape[1] != 2:
        raise ValueError(f"positions must have shape (N, 2), got {positions.shape}")
    gap = np.abs(positions[:, None, :] - positions[None, :, :]).max(axis=2)
    near = gap <= int(radius)
    np.fill_diagonal(near, False)
    return near


@dataclasses.dataclass(frozen=True)
class CooperativeReward:
    """Eq. 2: R_i = (1 - alpha) r_i + alpha * mean_{j in A_i} r_j, and R_i = r_i when A_i is empty.

    A_i: the other agents inside i's FOV, taken at the positions after the step (where the
    neighbours are when the reward is given).
    """

    alpha: float
    radius: int = 4

    def __post_init__(self):
        if isinstance(self.alpha, bool) or not isinstance(self.alpha, (int, float, np.floating)) \
                or not 0.0 <= float(self.alpha) <= 1.0:
            raise ValueError(f"CooperativeReward.alpha must be in [0, 1], got {self.alpha!r}")
        if not isinstance(self.radius, (int, np.integer)) or self.radius < 0:
            raise ValueError(f"CooperativeReward.radius must be an int >= 0, got {self.radius!r}")

    def __call__(self, rewards, positions) -> np.ndarray:
        rewards = np.asarray(rewards, dtype=np.float64)
        positions = np.asarray(positions)
        if rewards.shape != (positions.shape[0],):
            raise ValueError(f"rewards shape {rewards.shape} does not match "
                             f"{positions.shape[0]} agents")
        if self.alpha == 0.0:
            return rewards.astype(np.float32)
        near = fov_neighbours(positions, self.radius)
        count = near.sum(axis=1)
        neighbour_mean = (near @ rewards) / np.maximum(count, 1)
        mixed = (1.0 - self.alpha) * rewards + self.alpha * neighbour_mean
        return np.where(count > 0, mixed, rewards).astype(np.float32)
