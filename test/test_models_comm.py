"""Communication partners: DHC nearest partners (ties by index) and DCC relative positions."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mapf_fleet.models.comm import (
    dhc_partners, dhc_partners_torch, fov_neighbour_table, fov_neighbours, relative_position_index,
)


def brute_force_partners(positions, radius, k):
    out = np.full((len(positions), k), -1)
    for i, p in enumerate(positions):
        candidates = []
        for j, q in enumerate(positions):
            d = q - p
            if j != i and np.abs(d).max() <= radius:
                candidates.append((float(np.hypot(*d)), j))
        for slot, (_, j) in enumerate(sorted(candidates)[:k]):
            out[i, slot] = j
    return out


def test_ties_go_to_the_lower_index_and_order_is_nearest_first():
    # Agent 0 at the centre; 1 and 2 both at distance 1, 3 at distance 1 too, 4 at sqrt(2).
    positions = np.array([[5, 5], [5, 6], [4, 5], [6, 5], [4, 4]])
    np.testing.assert_array_equal(dhc_partners(positions, 4, 2)[0], [1, 2])
    # Swap the indices: the lower index still wins the tie.
    positions = np.array([[5, 5], [4, 4], [6, 5], [5, 6]])
    np.testing.assert_array_equal(dhc_partners(positions, 4, 2)[0], [2, 3])
    np.testing.assert_array_equal(dhc_partners(positions, 4, 3)[0], [2, 3, 1])


def test_fov_is_chebyshev_and_nearest_inside_it_is_taken():
    # (5, 0) is nearer by Euclid (5) than (4, 4) (5.66) but outside the FOV (Chebyshev 5).
    positions = np.array([[10, 10], [15, 10], [14, 14]])
    np.testing.assert_array_equal(dhc_partners(positions, 4, 2)[0], [2, -1])


def test_lonely_agents_and_padding_get_minus_one():
    positions = np.array([[0, 0], [20, 20], [0, 1]])
    np.testing.assert_array_equal(dhc_partners(positions, 4, 2),
                                  [[2, -1], [-1, -1], [0, -1]])
    masked = dhc_partners(positions, 4, 2, agent_mask=np.array([True, True, False]))
    np.testing.assert_array_equal(masked, [[-1, -1], [-1, -1], [-1, -1]])
    np.testing.assert_array_equal(dhc_partners(np.array([[3, 3]]), 4, 2), [[-1, -1]])


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 30), st.integers(3, 14), st.integers(1, 4), st.integers(0, 2**31 - 1))
def test_numpy_torch_and_brute_force_agree(num_agents, side, k, seed):
    rng = np.random.default_rng(seed)
    num_agents = min(num_agents, side * side)
    cells = rng.choice(side * side, num_agents, replace=False)
    positions = np.stack([cells // side, cells % side], 1)
    expected = brute_force_partners(positions, 4, k)
    np.testing.assert_array_equal(dhc_partners(positions, 4, k), expected)
    np.testing.assert_array_equal(
        dhc_partners_torch(torch.from_numpy(positions)[None], 4, k)[0].numpy(), expected)
    table = fov_neighbour_table(torch.from_numpy(positions)[None], 4)[0].numpy()
    for i in range(num_agents):
        indices, offsets = fov_neighbours(positions, i, 4)
        np.testing.assert_array_equal(table[i][table[i] >= 0], indices)
        np.testing.assert_array_equal(offsets, positions[indices] - positions[i])


def test_relative_position_index_is_row_major_from_the_top_left_corner():
    assert relative_position_index(np.array([-4, -4])) == 0
    assert relative_position_index(np.array([0, 0])) == 40  # the centre of the 9x9 FOV
    assert relative_position_index(np.array([-4, 3])) == 7
    assert relative_position_index(np.array([1, 0])) == 49
    assert relative_position_index(torch.tensor([4, 4])).item() == 80
    with pytest.raises(ValueError, match="outside radius"):
        relative_position_index(np.array([5, 0]))


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), batch=st.integers(1, 3), agents=st.integers(1, 80),
       side=st.integers(1, 24), radius=st.integers(1, 4), masked=st.booleans())
def test_the_neighbour_lookup_by_cell_equals_the_pair_table(seed, batch, agents, side, radius,
                                                           masked):
    from mapf_fleet.models.comm import (
        _fov_neighbour_table_by_cell, _fov_neighbour_table_by_pairs,
    )

    rng = np.random.default_rng(seed)
    agents = min(agents, side * side)
    cells = [rng.choice(side * side, agents, replace=False) for _ in range(batch)]
    positions = torch.from_numpy(np.stack([np.stack(np.divmod(c, side), 1) for c in cells])
                                 + rng.integers(-50, 50, size=2))
    mask = torch.from_numpy(rng.random((batch, agents)) < 0.7) if masked else None
    by_cell = _fov_neighbour_table_by_cell(positions, radius, mask)
    assert torch.equal(by_cell, _fov_neighbour_table_by_pairs(positions, radius, mask))


def test_agents_sharing_a_cell_fall_back_to_the_pair_table():
    from mapf_fleet.models.comm import SPATIAL_NEIGHBOURS_FROM, _fov_neighbour_table_by_cell

    rng = np.random.default_rng(3)
    positions = rng.integers(0, 40, size=(1, SPATIAL_NEIGHBOURS_FROM, 2))
    positions[0, 1] = positions[0, 0]  # two agents in one cell: both see each other
    positions = torch.from_numpy(positions)
    assert _fov_neighbour_table_by_cell(positions, 4) is None
    table = fov_neighbour_table(positions, 4)
    assert 1 in table[0, 0].tolist() and 0 in table[0, 1].tolist()
