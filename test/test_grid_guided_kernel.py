"""The compiled guided search (`grid.guided_kernel`) against scipy's Dijkstra on the same costs:
the same float64 rows bit for bit and the same heuristic bits as `heuristic._guided_bits`, under
one-way lanes, costs spanning many orders of magnitude, buckets that outgrow their room, batches
on several threads, and the guided `DistanceTable` built on it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse.csgraph import dijkstra

from mapf_fleet.grid.actions import move_targets
from mapf_fleet.grid.guidance import Guidance
from mapf_fleet.grid.guidance_made import CostModel, highways
from mapf_fleet.grid.guided_kernel import MAX_BUCKETS, GuidedSearcher
from mapf_fleet.grid.heuristic import UNREACHABLE, DistanceTable, _guided_bits


def _oracle(guidance: Guidance, goals) -> tuple[np.ndarray, np.ndarray]:
    """scipy's rows (inf where none) and `_guided_bits` for flat `goals` (obstacles too)."""
    h, w = guidance.shape
    graph = guidance.reverse_graph()
    rows = np.array([np.full(h * w, np.inf) if guidance.obstacles.flat[g]
                     else dijkstra(graph, directed=True, indices=int(g)) for g in goals])
    dist = np.where(np.isinf(rows), UNREACHABLE, rows).reshape(-1, h, w)
    return rows, _guided_bits(dist, guidance.costs).reshape(len(goals), -1)


def _raw(blocked: np.ndarray, costs: np.ndarray) -> Guidance:
    """A guidance graph without `from_costs`' checks: one-way moves may cut cells off (the
    search must give them inf, as scipy does)."""
    costs = np.where(np.isfinite(costs), costs, np.inf)
    targets = move_targets(blocked).reshape(*blocked.shape, 5)
    costs = np.where((targets >= 0) & ~blocked[..., None], costs, np.inf)
    return Guidance(blocked, costs)


def _assert_same(searcher: GuidedSearcher, guidance: Guidance, goals, label: str) -> None:
    rows, bits = searcher.search(goals)
    want_rows, want_bits = _oracle(guidance, goals)
    for k in range(len(goals)):
        # exactly scipy's float64 values (assert_array_equal: not even an ulp apart)
        np.testing.assert_array_equal(rows[k], want_rows[k], err_msg=f"{label} goal {k} row")
        np.testing.assert_array_equal(bits[k], want_bits[k], err_msg=f"{label} goal {k} bits")


def _random_costs(rng, shape, low, high, forbid: float) -> np.ndarray:
    """Log-uniform costs in [low, high]; a share `forbid` of the moves forbidden (inf)."""
    costs = np.exp(rng.uniform(np.log(low), np.log(high), (*shape, 5)))
    costs[..., 1:][rng.random((*shape, 4)) < forbid] = np.inf
    return costs


def test_rows_and_bits_equal_scipy_under_one_way_moves_and_cut_off_parts():
    rng = np.random.default_rng(11)
    for trial in range(40):
        h, w = (int(v) for v in rng.integers(1, 30, size=2))
        blocked = rng.random((h, w)) < rng.random() * 0.5
        guidance = _raw(blocked, _random_costs(rng, (h, w), 0.2, 5.0, forbid=0.3))
        goals = rng.integers(0, h * w, size=4)  # obstacles too
        _assert_same(GuidedSearcher(blocked, guidance.step_costs(), threads=1), guidance,
                     goals, f"trial {trial}")


@pytest.mark.parametrize("low, high", [(1e-3, 1e3), (1e-6, 1.0), (1e-20, 1.0), (0.1, 0.3),
                                       (7.0, 7.0), (1e305, 1e307)])
def test_rows_are_exact_whatever_the_costs_span(low, high):
    """Costs spanning more than `MAX_BUCKETS` least costs widen the buckets (cells of a bucket
    correct each other), down to moves too cheap to change a sum; costs like 0.1 and 0.3 sum
    with rounding at the buckets' edges; one cost everywhere is a BFS scaled; costs whose sums
    overflow to inf leave far cells out of reach. All give scipy's values exactly."""
    rng = np.random.default_rng(int(np.log10(low) * 7 + np.log10(high)) % 97)
    blocked = rng.random((36, 44)) < 0.25
    costs = _random_costs(rng, blocked.shape, low, high, forbid=0.0)
    if low == 0.1:
        costs = np.round(costs, 1)  # 0.1, 0.2, 0.3: sums that are not exact in binary
    guidance = _raw(blocked, costs)
    searcher = GuidedSearcher(blocked, guidance.step_costs(), threads=1)
    assert searcher.buckets <= MAX_BUCKETS
    _assert_same(searcher, guidance, np.flatnonzero(~blocked.ravel())[::97], f"{low}-{high}")


def test_the_fleets_guidance_graphs_give_scipys_rows():
    rng = np.random.default_rng(4)
    blocked = rng.random((64, 64)) < 0.2
    model = CostModel.from_vector(rng.normal(0, 0.5, len(CostModel.zeros().vector())))
    goals = rng.choice(np.flatnonzero(~blocked.ravel()), 12, replace=False)
    for guidance in (highways(blocked), model.guidance(blocked)):
        _assert_same(GuidedSearcher(blocked, guidance.step_costs(), threads=1), guidance,
                     goals, guidance.meta.get("kind", "model"))


def test_a_bucket_that_outgrows_its_room_is_searched_again_with_more():
    rng = np.random.default_rng(6)
    blocked = rng.random((50, 50)) < 0.1
    guidance = highways(blocked)
    searcher = GuidedSearcher(blocked, guidance.step_costs(), threads=1)
    searcher.room = 2
    _assert_same(searcher, guidance, [0, 1234, 2499], "small room")
    assert searcher.room > 2  # grown, and kept for the next searches


def test_a_batch_on_several_threads_equals_one_goal_at_a_time():
    rng = np.random.default_rng(9)
    blocked = rng.random((40, 52)) < 0.3
    guidance = _raw(blocked, _random_costs(rng, blocked.shape, 0.5, 4.0, forbid=0.1))
    goals = rng.integers(0, blocked.size, size=41)
    alone = [GuidedSearcher(blocked, guidance.step_costs(), threads=1).search([g]) for g in goals]
    rows, bits = GuidedSearcher(blocked, guidance.step_costs(), threads=4).search(goals)
    for k, (row, bit) in enumerate(alone):
        np.testing.assert_array_equal(rows[k], row[0])
        np.testing.assert_array_equal(bits[k], bit[0])


def test_the_guided_table_serves_rows_arrays_and_bits_of_one_search():
    rng = np.random.default_rng(2)
    blocked = rng.random((30, 34)) < 0.3
    guidance = highways(blocked)
    table = DistanceTable(blocked, guidance)
    goals = [int(g) for g in rng.integers(0, blocked.size, size=15)]
    table.prepare(goals)
    searched = table.searches
    want_rows, want_bits = _oracle(guidance, goals)
    np.testing.assert_array_equal(table.bits_of(goals).reshape(len(goals), -1), want_bits)
    for k, goal in enumerate(goals):
        array = table.array(goal)
        assert array.dtype == np.float64 and not array.flags.writeable
        np.testing.assert_array_equal(array, np.where(np.isinf(want_rows[k]), UNREACHABLE,
                                                      want_rows[k]))
        row = table.row(goal)
        assert isinstance(row[0], float) and table.unreachable == np.inf
        np.testing.assert_array_equal(np.asarray(row), want_rows[k])
    assert table.searches == searched  # rows, arrays and bits all came from the batch


def test_bad_step_costs_are_refused_in_one_line():
    blocked = np.zeros((3, 3), dtype=bool)
    with pytest.raises(ValueError, match="step costs are for 4 cells, the map has 9"):
        GuidedSearcher(blocked, np.ones((4, 5)))
    costs = np.ones((9, 5))
    costs[4, 1] = 0.0
    with pytest.raises(ValueError, match="move costs must be > 0, got 0"):
        GuidedSearcher(blocked, costs)


def test_costs_given_for_moves_that_do_not_exist_are_ignored():
    """Step costs of 1 everywhere, off the map and around obstacles too: the search stays on the
    map's free cells (it would run off the padded map otherwise) and gives the unit graph's
    rows, and no bits where the goal is out of reach."""
    rng = np.random.default_rng(13)
    blocked = rng.random((23, 17)) < 0.35
    unit = _raw(blocked, np.ones((*blocked.shape, 5)))  # ones where a move exists, else inf
    searcher = GuidedSearcher(blocked, np.ones((blocked.size, 5)), threads=1)
    _assert_same(searcher, unit, rng.integers(0, blocked.size, size=6), "ones everywhere")
