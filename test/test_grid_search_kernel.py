"""The compiled breadth-first search (`grid.search_kernel`) against scipy's graph search: its
distance rows, its heuristic bits (one pass), its batches on several threads, and the
`DistanceTable` views built on it (`row`, `array`, `bits_of`)."""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import shortest_path

from grid_oracle import adjacency as _adjacency
from mapf_fleet.grid.heuristic import UNREACHABLE, DistanceTable, _bits_from_distances
from mapf_fleet.grid.search_kernel import Searcher


def _oracle(grid: np.ndarray, flat: np.ndarray) -> np.ndarray:
    h, w = grid.shape
    dist = shortest_path(_adjacency(grid), method="D", unweighted=True, indices=flat)
    dist = np.where(np.isinf(dist), -1, dist).astype(np.int32).reshape(-1, h, w)
    dist[grid.reshape(-1)[flat]] = -1  # a goal on an obstacle: nothing reaches it
    return dist


def test_rows_and_bits_equal_scipy_on_random_maps_with_cut_off_parts():
    rng = np.random.default_rng(3)
    for trial in range(60):
        h, w = (int(v) for v in rng.integers(1, 40, size=2))
        grid = rng.random((h, w)) < rng.random() * 0.7  # dense ones fall apart into pieces
        flat = rng.integers(0, h * w, size=5)  # obstacles too
        expected = _oracle(grid, flat)
        searcher = Searcher(grid, threads=1)
        assert searcher.unreachable == h * w + 1 and searcher.dtype == np.int16  # small maps
        rows, bits = searcher.search(flat)
        for k in range(len(flat)):
            want = np.where(expected[k] < 0, h * w + 1, expected[k]).reshape(-1)
            np.testing.assert_array_equal(rows[k], want, err_msg=f"trial {trial} goal {k}")
            np.testing.assert_array_equal(bits[k], _bits_from_distances(expected[k][None])[0].reshape(-1),
                                          err_msg=f"trial {trial} goal {k}")


def test_a_batch_on_several_threads_equals_one_goal_at_a_time():
    rng = np.random.default_rng(5)
    grid = rng.random((48, 64)) < 0.3
    flat = rng.integers(0, grid.size, size=97)
    alone = [Searcher(grid, threads=1).search([g]) for g in flat]
    rows, bits = Searcher(grid, threads=4).search(flat)
    for k, (row, bit) in enumerate(alone):
        np.testing.assert_array_equal(rows[k], row[0])
        np.testing.assert_array_equal(bits[k], bit[0])


def test_the_table_serves_rows_arrays_and_bits_of_one_search():
    rng = np.random.default_rng(8)
    grid = rng.random((30, 30)) < 0.35
    table = DistanceTable(grid)
    flat = [int(g) for g in rng.integers(0, grid.size, size=20)]
    table.prepare(flat)
    searched = table.searches
    expected = _oracle(grid, np.array(flat))
    np.testing.assert_array_equal(table.bits_of(flat), _bits_from_distances(expected))
    for k, goal in enumerate(flat):
        array = table.array(goal)
        np.testing.assert_array_equal(array, expected[k].reshape(-1))
        assert not array.flags.writeable
        row = table.row(goal)
        assert row.readonly and isinstance(row[0], int)
        assert [row[c] for c in range(grid.size)] == \
            np.where(expected[k].reshape(-1) == UNREACHABLE, table.unreachable, expected[k].reshape(-1)).tolist()
    assert table.searches == searched  # every view came from the batch's one search


def _serpentine(side: int) -> np.ndarray:
    """A one-cell corridor winding through a side x side map: paths of about side^2 / 2 steps."""
    grid = np.zeros((side, side), dtype=bool)
    grid[1::4, :-1] = True
    grid[3::4, 1:] = True
    return grid


def test_rows_are_int16_only_where_no_path_can_reach_32767_steps():
    rng = np.random.default_rng(2)
    open_map = rng.random((200, 200)) < 0.25  # 40,000 cells, paths of a few hundred steps
    winding = _serpentine(260)  # 67,600 cells, paths of over 30,000 steps
    for grid, dtype, unreachable in ((open_map, np.int16, 32767),
                                     (winding, np.int32, winding.size + 1)):
        searcher = Searcher(grid, threads=1)
        assert (searcher.dtype, searcher.unreachable) == (dtype, unreachable)
        flat = np.flatnonzero(~grid.reshape(-1))[[0, -1]]  # the two ends of the corridor
        expected = _oracle(grid, flat)
        rows, _ = searcher.search(flat)
        for k in range(len(flat)):
            want = np.where(expected[k] < 0, unreachable, expected[k]).reshape(-1)
            np.testing.assert_array_equal(rows[k], want)
        assert rows[0].dtype == dtype
    assert expected.max() > 32767  # the winding map needs int32


def test_bounded_windows_equal_the_whole_search_around_their_centres():
    """`Searcher.windows` (A* bounded to a window and one ring around it) gives exactly the
    whole search's distances and padded static bytes there: maps that fall apart into pieces,
    goals on obstacles and inside the window, windows over the map's edge, both threads."""
    from mapf_fleet.grid.search_kernel import fill_static

    rng = np.random.default_rng(5)
    for trial in range(40):
        h, w = (int(v) for v in rng.integers(1, 45, size=2))
        grid = rng.random((h, w)) < rng.random() * 0.7
        n = int(rng.integers(1, 24))
        flat = rng.integers(0, h * w, size=n)  # obstacles too
        centres = np.stack([rng.integers(0, h, n), rng.integers(0, w, n)], 1)
        half = int(rng.integers(0, 7))
        searcher = Searcher(grid, threads=int(rng.integers(1, 3)))
        static, dist, settled = searcher.windows(flat, centres, half)
        expected = _oracle(grid, flat)
        s = 2 * half + 1
        blocked = grid.reshape(-1).view(np.uint8)
        for k in range(n):
            padded = np.empty((h + 2 * half) * (w + 2 * half), np.uint8)
            fill_static(blocked, _bits_from_distances(expected[k][None])[0].reshape(-1),
                        padded, h, w, half)
            r, c = centres[k]
            want = padded.reshape(h + 2 * half, w + 2 * half)[r:r + s, c:c + s]
            np.testing.assert_array_equal(static[k].reshape(s, s), want,
                                          err_msg=f"trial {trial} goal {k}")
            far = np.full((h + 2 * half, w + 2 * half), -1, np.int32)
            far[half:half + h, half:half + w] = expected[k]
            np.testing.assert_array_equal(dist[k].reshape(s, s), far[r:r + s, c:c + s],
                                          err_msg=f"trial {trial} goal {k}")
        assert settled <= n * int((~grid).sum())


def test_a_bounded_window_settles_a_fraction_of_a_large_map():
    """What the first tick at scale pays for: a window 40 steps from its goal on an open 200x200
    map settles a few of its 40,000 cells (the whole search settles them all)."""
    grid = np.zeros((200, 200), dtype=bool)
    grid[20, 90:111] = True  # a wall between them to go round
    searcher = Searcher(grid, threads=1)
    _, dist, settled = searcher.windows([100], [(40, 100)], 8)  # goal (0, 100)
    assert dist.reshape(17, 17)[8, 8] == 40 + 2 * 11
    assert settled < 0.1 * grid.size


def test_a_windowed_goal_reads_as_its_whole_row_and_is_searched_whole_outside_it():
    """`DistanceTable.open_windows`: `row` serves the window's cells without a whole search,
    a read outside it searches the goal whole (and the window goes), `numpy.asarray` gives the
    whole row; values equal the whole search's everywhere."""
    rng = np.random.default_rng(9)
    grid = rng.random((40, 50)) < 0.3
    free = np.flatnonzero(~grid.reshape(-1))
    goals = rng.choice(free, 6, replace=False)
    centres = np.argwhere(~grid)[rng.choice(len(free), 6, replace=False)]
    whole = DistanceTable(grid)
    table = DistanceTable(grid)
    table.open_windows(goals, centres, 5)
    assert table.searches == 0 and table.windows.cells > 0
    for g, (r, c) in zip(goals.tolist(), centres.tolist()):
        row, want = table.row(g), whole.row(g)
        inside = [(r + dr) * 50 + c + dc for dr in range(-5, 6) for dc in range(-5, 6)
                  if 0 <= r + dr < 40 and 0 <= c + dc < 50]
        assert [row[k] for k in inside] == [want[k] for k in inside]
        assert table.searches == 0 and table.windows.get(g) is not None
    g = int(goals[0])
    r, c = centres[0]
    outside = ((r + 20) % 40) * 50 + (c + 25) % 50
    assert table.row(g)[outside] == whole.row(g)[outside]
    assert table.searches == 1 and table.windows.get(g) is None
    np.testing.assert_array_equal(np.asarray(table.row(int(goals[1]))),
                                  np.asarray(whole.row(int(goals[1]))))
    assert table.windows.get(int(goals[1])) is None


def test_a_search_writing_padded_maps_writes_fill_statics_bytes():
    """`Searcher.search(goals, statics, pad)`: the padded static bytes the observations' pool
    keeps, written by the search itself, equal `fill_static` of the search's bits."""
    from mapf_fleet.grid.search_kernel import fill_static

    rng = np.random.default_rng(13)
    for trial in range(20):
        h, w = (int(v) for v in rng.integers(1, 30, size=2))
        grid = rng.random((h, w)) < rng.random() * 0.6
        pad = int(rng.integers(0, 5))
        flat = rng.integers(0, h * w, size=int(rng.integers(1, 20)))
        searcher = Searcher(grid, threads=int(rng.integers(1, 3)))
        rows, bits = searcher.search(flat)
        statics = [np.full((h + 2 * pad) * (w + 2 * pad), 77, np.uint8) for _ in flat]
        rows_too, none = searcher.search(flat, statics, pad)
        assert none is None
        for k in range(len(flat)):
            want = np.empty_like(statics[k])
            fill_static(grid.reshape(-1).view(np.uint8), bits[k], want, h, w, pad)
            np.testing.assert_array_equal(statics[k], want, err_msg=f"trial {trial} goal {k}")
            np.testing.assert_array_equal(rows_too[k], rows[k])
