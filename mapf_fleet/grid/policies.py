"""The non-learned reference policy: follow the heuristic channels, stay when blocked."""

from __future__ import annotations

import numpy as np

from .actions import ACTION_DELTAS, NUM_ACTIONS


def heuristic_policy(obs) -> np.ndarray:
    """int64 actions (...,) from observations (..., 6, S, S).

    For each move in action order (up, down, left, right), the move is allowed when the agent's
    heuristic bit for it is set at its own cell (the target is free and closer to the goal) and
    the target cell holds no agent in the FOV. The first allowed move is taken; with none (on the
    goal, or all closer cells occupied) the agent stays.
    """
    obs = np.asarray(obs)
    if obs.ndim < 3 or obs.shape[-3] != 6 or obs.shape[-1] != obs.shape[-2] \
            or obs.shape[-1] % 2 != 1:
        raise ValueError(f"obs must have shape (..., 6, S, S) with odd S, got {obs.shape}")
    c = obs.shape[-1] // 2
    heuristic = obs[..., 2:6, c, c] != 0                                   # (..., 4)
    rows = c + ACTION_DELTAS[1:, 0]
    cols = c + ACTION_DELTAS[1:, 1]
    occupied = obs[..., 0, rows, cols] != 0                                 # (..., 4)
    allowed = heuristic & ~occupied
    first = np.argmax(allowed, axis=-1) + 1
    return np.where(allowed.any(axis=-1), first, 0).astype(np.int64)


def random_policy(obs, rng) -> np.ndarray:
    """Uniform random actions for each agent of `obs` (..., 6, S, S); used by benchmarks."""
    return rng.integers(0, NUM_ACTIONS, size=np.asarray(obs).shape[:-3])
