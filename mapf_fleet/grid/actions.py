"""Actions in DHC order (the project's fixed convention, see docs/architecture.md).

DCC's reference code orders them differently (up, down, left, right, stay); convert only at the
edge, e.g. when importing a reference checkpoint.
"""

from __future__ import annotations

import numpy as np

STAY, UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3, 4
NUM_ACTIONS = 5
ACTION_NAMES = ("stay", "up", "down", "left", "right")

# (row, col) displacement of each action; row grows downwards.
ACTION_DELTAS = np.array([[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]], dtype=np.int64)
ACTION_DELTAS.setflags(write=False)


def actions_between(positions, targets) -> np.ndarray:
    """(N,) the action moving each agent from `positions` (N, 2) to `targets` (N, 2); STAY where
    no single action does (it held, or jumped)."""
    delta = np.asarray(targets, dtype=np.int64) - np.asarray(positions, dtype=np.int64)
    match = (delta[:, None, :] == ACTION_DELTAS[None]).all(axis=-1)  # (N, 5)
    return np.where(match.any(axis=1), match.argmax(axis=1), STAY).astype(np.int64)


def move_targets(blocked: np.ndarray) -> np.ndarray:
    """(H*W, 5) int64: the flat cell each action leads to from each flat cell of the (H, W)
    bool map `blocked` (True = obstacle), -1 where it leaves the map or enters an obstacle."""
    h, w = blocked.shape
    rows, cols = np.divmod(np.arange(h * w), w)
    tr = rows[:, None] + ACTION_DELTAS[:, 0]
    tc = cols[:, None] + ACTION_DELTAS[:, 1]
    inside = (tr >= 0) & (tr < h) & (tc >= 0) & (tc < w)
    flat = np.where(inside, tr * w + tc, 0)
    return np.where(inside & ~blocked.ravel()[flat], flat, -1)
