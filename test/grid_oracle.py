"""The tests' oracle for the compiled searches: scipy's graph form of a map."""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix


def adjacency(blocked: np.ndarray) -> csr_matrix:
    """Symmetric 4-connected adjacency of the free cells of `blocked` (H, W) bool."""
    h, w = blocked.shape
    free = ~blocked
    index = np.arange(h * w).reshape(h, w)
    horizontal = free[:, :-1] & free[:, 1:]
    vertical = free[:-1, :] & free[1:, :]
    rows = np.concatenate([index[:, :-1][horizontal], index[:-1, :][vertical]])
    cols = np.concatenate([index[:, 1:][horizontal], index[1:, :][vertical]])
    both = (np.concatenate([rows, cols]), np.concatenate([cols, rows]))
    graph = csr_matrix((np.ones(2 * rows.size), both), shape=(h * w, h * w))
    graph.sum_duplicates()
    return graph
