"""Who talks to whom: communication partners computed from positions only.

The numpy functions are what a ROS policy node runs on the shared fleet state; the batched
networks use the torch twins below, which apply exactly the same rules, so a robot and the
batched evaluator always agree on the partners.

Conventions: positions are (row, col) ints; agent j is inside agent i's FOV when j != i and
max(|dr|, |dc|) <= radius (Chebyshev), as in docs/architecture.md.
"""

from __future__ import annotations

import numpy as np
import torch


def _as_positions(positions: np.ndarray) -> np.ndarray:
    positions = np.asarray(positions)
    if positions.ndim < 2 or positions.shape[-1] != 2:
        raise ValueError(f"positions: expected shape (..., N, 2), got {positions.shape}")
    if not np.issubdtype(positions.dtype, np.integer):
        raise ValueError(f"positions: expected integer (row, col), got dtype {positions.dtype}")
    return positions.astype(np.int64, copy=False)


def _pair_keys(positions: np.ndarray, radius: int, agent_mask: np.ndarray | None) -> np.ndarray:
    """Sort key of every (i, j) pair: squared distance * N + j; -1 where j is not a candidate.

    Squared Euclidean distances are integers, so `d2 * N + j` orders by distance and then by the
    lower index, with no float ties anywhere (the same key in numpy and torch).
    """
    num_agents = positions.shape[-2]
    delta = positions[..., None, :, :] - positions[..., :, None, :]  # [i, j] = pos j - pos i
    in_fov = (np.abs(delta) <= radius).all(-1)
    in_fov &= ~np.eye(num_agents, dtype=bool)
    if agent_mask is not None:
        agent_mask = np.asarray(agent_mask, dtype=bool)
        in_fov &= agent_mask[..., :, None] & agent_mask[..., None, :]
    d2 = (delta**2).sum(-1)
    keys = d2 * num_agents + np.arange(num_agents)
    return np.where(in_fov, keys, -1)


def dhc_partners(
    positions: np.ndarray, radius: int = 4, k: int = 2, agent_mask: np.ndarray | None = None
) -> np.ndarray:
    """The k nearest other agents inside each agent's FOV: int64 (..., N, k), -1 for none.

    Nearest by Euclidean distance, ties broken by the lower agent index; partners are listed
    nearest first. Padded agents (agent_mask False) neither have nor are partners.
    """
    positions = _as_positions(positions)
    keys = _pair_keys(positions, radius, agent_mask)
    big = np.iinfo(np.int64).max
    order = np.argsort(np.where(keys >= 0, keys, big), axis=-1, kind="stable")[..., :k]
    chosen = np.take_along_axis(keys, order, axis=-1) >= 0
    partners = np.where(chosen, order, -1)
    if partners.shape[-1] < k:  # fewer agents than k
        pad = np.full(partners.shape[:-1] + (k - partners.shape[-1],), -1, dtype=np.int64)
        partners = np.concatenate([partners, pad], axis=-1)
    return partners.astype(np.int64)


def fov_neighbours(
    positions: np.ndarray, index: int, radius: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """Agent `index`'s FOV neighbours in index order: (indices (M,), offsets (M, 2)).

    offsets[m] = position of neighbour m - position of agent `index` (where the neighbour sits
    in the agent's FOV, relative to its centre). This is what a DCC robot needs for its
    decision-causal check.
    """
    positions = _as_positions(positions)
    delta = positions - positions[index]
    inside = (np.abs(delta) <= radius).all(-1)
    inside[index] = False
    indices = np.flatnonzero(inside)
    return indices, delta[indices]


def relative_position_index(offset, radius: int = 4):
    """Index of a relative offset (sender - receiver, (..., 2)) in the (2r+1)^2 one-hot.

    Row-major over the receiver's FOV: (dr + r) * (2r + 1) + (dc + r); offset (0, 0) (a message
    from oneself) is the centre cell. Works on numpy arrays and torch tensors.
    """
    if isinstance(offset, torch.Tensor):
        if bool((offset.abs() > radius).any()):
            raise ValueError(f"relative_position_index: offset outside radius {radius}: {offset}")
        return (offset[..., 0] + radius) * (2 * radius + 1) + (offset[..., 1] + radius)
    offset = np.asarray(offset)
    if offset.shape[-1:] != (2,):
        raise ValueError(f"relative_position_index: expected shape (..., 2), got {offset.shape}")
    if (np.abs(offset) > radius).any():
        raise ValueError(f"relative_position_index: offset outside radius {radius}: {offset}")
    return (offset[..., 0] + radius) * (2 * radius + 1) + (offset[..., 1] + radius)


# ---- torch twins for the batched networks -------------------------------------------------


def _pair_keys_torch(
    positions: torch.Tensor, radius: int, agent_mask: torch.Tensor | None
) -> torch.Tensor:
    """Same keys as `_pair_keys`, for (B, N, 2) long positions: (B, N, N), -1 = not candidate."""
    num_agents = positions.shape[-2]
    delta = positions[:, None, :, :] - positions[:, :, None, :]
    in_fov = (delta.abs() <= radius).all(-1)
    in_fov &= ~torch.eye(num_agents, dtype=torch.bool, device=positions.device)
    if agent_mask is not None:
        in_fov &= agent_mask[:, :, None] & agent_mask[:, None, :]
    keys = (delta * delta).sum(-1) * num_agents + torch.arange(num_agents, device=positions.device)
    return torch.where(in_fov, keys, torch.full_like(keys, -1))


def dhc_partners_torch(
    positions: torch.Tensor, radius: int, k: int, agent_mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Batched `dhc_partners`: (B, N, 2) long -> (B, N, k) long, -1 for none."""
    keys = _pair_keys_torch(positions, radius, agent_mask)
    big = torch.iinfo(torch.int64).max
    masked = torch.where(keys >= 0, keys, torch.full_like(keys, big))
    take = min(k, keys.shape[-1])
    sorted_keys, order = torch.topk(masked, take, dim=-1, largest=False, sorted=True)
    partners = torch.where(sorted_keys != big, order, torch.full_like(order, -1))
    if take < k:
        pad = partners.new_full(partners.shape[:-1] + (k - take,), -1)
        partners = torch.cat([partners, pad], dim=-1)
    return partners


# Above this many agents an episode's FOV neighbours come from a lookup of the agents' cells
# (O(N (2r+1)^2)) instead of the N x N pair table (both give the same table).
SPATIAL_NEIGHBOURS_FROM = 256


def fov_neighbour_table(
    positions: torch.Tensor, radius: int, agent_mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Every agent's FOV neighbours in index order, padded: (B, N, K) long, -1 = empty slot.

    K is the largest neighbour count in the batch (at least 1), so memory grows with the local
    density, not with N^2.
    """
    if positions.shape[-2] >= SPATIAL_NEIGHBOURS_FROM:
        table = _fov_neighbour_table_by_cell(positions, radius, agent_mask)
        if table is not None:
            return table
    return _fov_neighbour_table_by_pairs(positions, radius, agent_mask)


def _fov_neighbour_table_by_pairs(
    positions: torch.Tensor, radius: int, agent_mask: torch.Tensor | None = None
) -> torch.Tensor:
    keys = _pair_keys_torch(positions, radius, agent_mask)
    inside = keys >= 0
    width = max(int(inside.sum(-1).max()) if inside.numel() else 0, 1)
    num_agents = positions.shape[-2]
    index = torch.arange(num_agents, device=positions.device).expand_as(keys)
    # Sort candidates first (in index order) by giving non-candidates a key past every index.
    rank = torch.where(inside, index, index + num_agents)
    order = torch.argsort(rank, dim=-1)[..., :width]
    valid = torch.gather(inside, -1, order)
    return torch.where(valid, order, torch.full_like(order, -1))


def _fov_neighbour_table_by_cell(
    positions: torch.Tensor, radius: int, agent_mask: torch.Tensor | None = None
) -> torch.Tensor | None:
    """`fov_neighbour_table` from the sorted cells of the agents: each agent looks up the
    (2r+1)^2 - 1 cells around its own. None when two agents share a cell (the pair table
    handles that)."""
    batch, num_agents = positions.shape[:2]
    device = positions.device
    flat = positions.reshape(-1, 2)
    valid = torch.ones(batch * num_agents, dtype=torch.bool, device=device) \
        if agent_mask is None else agent_mask.reshape(-1).bool()
    table = torch.full((batch * num_agents, 1), -1, dtype=torch.long, device=device)
    agents = valid.nonzero(as_tuple=True)[0]
    if agents.numel() == 0:
        return table.view(batch, num_agents, 1)
    cells = flat[agents]
    low = cells.min(0).values
    # every cell r away from an agent stays inside its own episode's block and row
    extent = cells.max(0).values - low + 1 + 2 * radius
    rows, cols = int(extent[0]), int(extent[1])
    key = (agents // num_agents) * (rows * cols) + (cells[:, 0] - low[0] + radius) * cols \
        + (cells[:, 1] - low[1] + radius)
    sorted_keys, order = torch.sort(key)
    if bool((sorted_keys[1:] == sorted_keys[:-1]).any()):
        return None
    span = torch.arange(-radius, radius + 1, device=device)
    shifts = (span[:, None] * cols + span[None, :]).reshape(-1)
    shifts = shifts[shifts != 0]
    wanted = key[:, None] + shifts  # (M, (2r+1)^2 - 1)
    at = torch.searchsorted(sorted_keys, wanted).clamp(max=sorted_keys.numel() - 1)
    hit = sorted_keys[at] == wanted
    neighbour = agents[order[at]] % num_agents
    ranked = torch.sort(torch.where(hit, neighbour, neighbour + num_agents), dim=-1).values
    width = max(int(hit.sum(-1).max()), 1)
    ranked = ranked[:, :width]
    ranked = torch.where(ranked < num_agents, ranked, torch.full_like(ranked, -1))
    table = torch.full((batch * num_agents, width), -1, dtype=torch.long, device=device)
    table[agents] = ranked
    return table.view(batch, num_agents, width)
