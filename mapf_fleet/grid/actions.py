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
