"""The one observation builder (`grid.observation.ObservationBuilder`): what a fleet process
builds for the robots it hosts (`observe(positions, agents)`, built `for_goals` of those robots)
equals the grid world's `observe` of the whole fleet, for both observations; a builder of
several maps refuses the one-map call."""

from __future__ import annotations

import numpy as np
import pytest

from mapf_fleet.grid.actions import ACTION_DELTAS
from mapf_fleet.grid.env import EnvConfig, MAPFEnv, observe
from mapf_fleet.grid.heuristic import bfs_distances_many, cached_heuristic_channels
from mapf_fleet.grid.instance import generate_instance
from mapf_fleet.grid.observation import ObservationBuilder


def test_a_subset_of_robots_sees_what_observe_gives_them():
    instance = generate_instance(12, 10, 0.3, 4)
    grid, goals = np.asarray(instance.grid), np.asarray(instance.goals)
    positions = np.asarray(instance.starts)
    local = np.array([7, 2, 9])  # any order: rows follow `local`
    expected = observe(grid, positions, goals, cached_heuristic_channels(grid, goals), 4)[local]
    builder = ObservationBuilder.for_goals(grid, goals[local], 4)
    np.testing.assert_array_equal(builder.observe(positions, local), expected)
    # robots near the border see off-map cells as obstacles, and others in channel 0
    assert expected[:, 0].sum() > 0
    # every robot: the environment's observation
    env = MAPFEnv(instance)
    np.testing.assert_array_equal(ObservationBuilder.for_goals(grid, goals).observe(positions),
                                  env.reset())


def test_cost_to_go_observation_follows_the_goals():
    """A model reading "cost_to_go" gets observe()'s 7th channel; goals given at run time make
    a new builder (its key differs), whose distances are the new goals'."""
    instance = generate_instance(12, 10, 0.3, 5)
    grid, positions = np.asarray(instance.grid), np.asarray(instance.starts)
    local = np.array([3, 8, 0])
    keys = set()
    for goals in (np.asarray(instance.goals), np.asarray(instance.goals)[::-1].copy()):
        expected = observe(grid, positions, goals, cached_heuristic_channels(grid, goals), 4,
                           distances=bfs_distances_many(grid, goals))[local]
        builder = ObservationBuilder.for_goals(grid, goals[local], 4, "cost_to_go")
        keys.add(builder.key)
        assert builder.observe(positions, local).shape == (3, 7, 9, 9)
        np.testing.assert_array_equal(builder.observe(positions, local), expected)
        env = MAPFEnv(instance, EnvConfig(observation="cost_to_go"))
        if goals is instance.goals:
            np.testing.assert_array_equal(env.reset()[local], expected)
    assert len(keys) == 2


def test_bad_calls_say_what_is_wrong():
    instance = generate_instance(8, 4, 0.2, 1)
    builder = ObservationBuilder.for_goals(instance.grid, instance.goals[:2], 4)
    with pytest.raises(ValueError, match="3 agents for a builder of 2"):
        builder.observe(instance.starts, [0, 1, 2])
    with pytest.raises(ValueError, match="observation must be one of"):
        ObservationBuilder.for_goals(instance.grid, instance.goals, 4, "lidar")
    two_maps = ObservationBuilder(np.stack([instance.grid] * 2), np.zeros((2, 8, 8), np.uint8),
                                  4, np.array([0, 1]))
    with pytest.raises(ValueError, match="one map"):
        two_maps.observe(instance.starts[:2])


@pytest.mark.parametrize("window_from", [None, 0])
@pytest.mark.parametrize("observation", ["paper", "cost_to_go"])
def test_the_goal_observer_equals_a_builder_rebuilt_for_every_step(observation, window_from):
    """window_from 0: every batch of new goals is first searched in windows around its agents
    (the agents jump here: most windows are searched whole at once)."""
    from mapf_fleet.grid.heuristic import HeuristicCache
    from mapf_fleet.grid.goal_observer import GoalObserver

    rng = np.random.default_rng(7)
    for trial in range(12):
        h, w = rng.integers(3, 24, size=2)
        grid = rng.random((h, w)) < 0.3
        free = np.argwhere(~grid)
        if len(free) < 2:
            continue
        n = int(rng.integers(1, min(len(free), 12) + 1))
        observer = GoalObserver(grid, 4, observation, spare=int(rng.integers(0, 3)),
                                window_from=window_from)
        goals = free[rng.integers(0, len(free), n)]
        for step in range(8):  # a few goals change each step, some come back
            positions = free[rng.choice(len(free), n, replace=False)]
            change = rng.random(n) < 0.4
            goals[change] = np.argwhere(np.ones((h, w)))[rng.integers(0, h * w, change.sum())]
            agents = np.sort(rng.choice(n, int(rng.integers(1, n + 1)), replace=False))
            expected = ObservationBuilder.for_goals(grid, goals[agents], 4, observation,
                                                    HeuristicCache()).observe(positions, agents)
            got = observer.observe(positions, goals[agents], agents)
            assert got.dtype == expected.dtype
            np.testing.assert_array_equal(got, expected, err_msg=f"trial {trial} step {step}")
    assert observer.searched > 0


@pytest.mark.parametrize("observation", ["paper", "cost_to_go"])
def test_windows_hold_walking_agents_until_their_goals_are_searched_whole(observation,
                                                                          monkeypatch):
    """A first tick's goals searched in windows (`window_from` 0): agents walking a cell a step
    see what a rebuilt builder shows, every window is searched whole within `WINDOW_MARGIN`
    observations (beside the ticks, on a thread of the observer's), and the bounded searches
    settle fewer cells than whole searches would."""
    from collections import OrderedDict

    from mapf_fleet.grid import heuristic
    from mapf_fleet.grid.heuristic import DistanceTable, distance_table
    from mapf_fleet.grid.goal_observer import WINDOW_MARGIN, GoalObserver

    monkeypatch.setattr(heuristic, "_TABLES", OrderedDict())  # no goal searched whole before

    rng = np.random.default_rng(3)
    for trial in range(6):
        side = int(rng.integers(30, 60))
        grid = rng.random((side, side)) < 0.3
        free = np.argwhere(~grid)
        n = 24
        observer = GoalObserver(grid, 4, observation, window_from=0)
        positions = free[rng.choice(len(free), n, replace=False)]
        goals = free[rng.integers(0, len(free), n)]
        before = distance_table(grid).windows.cells
        beside = 0
        oracle = DistanceTable(grid)  # its own: the shared table's whole searches end windows
        bits = oracle.bits_of(goals[:, 0] * side + goals[:, 1])
        dist = oracle.many(goals) if observation == "cost_to_go" else None
        for step in range(WINDOW_MARGIN + 2):
            expected = ObservationBuilder(grid, bits, 4, distances=dist).observe(positions)
            got = observer.observe(positions, goals)
            np.testing.assert_array_equal(got, expected, err_msg=f"trial {trial} step {step}")
            beside += observer._pending is not None  # whole searches running beside the tick
            if step == 0:
                assert observer.windowed == len(np.unique(goals[:, 0] * side + goals[:, 1]))
                assert observer.searched == 0
            moves = ACTION_DELTAS[rng.integers(0, 5, n)]
            nxt = positions + moves
            ok = (nxt >= 0).all(1) & (nxt < side).all(1)
            ok[ok] &= ~grid[nxt[ok, 0], nxt[ok, 1]]
            positions = np.where(ok[:, None], nxt, positions)  # overlaps do not matter here
        assert not observer._window_of, "every window searched whole within the margin"
        assert beside > 0
        settled = distance_table(grid).windows.cells - before
        assert 0 < settled < observer.windowed * (~grid).sum()


def test_bfs_distances_equal_scipy_dijkstra_on_random_maps():
    from scipy.sparse.csgraph import shortest_path

    from grid_oracle import adjacency as _adjacency

    rng = np.random.default_rng(11)
    for trial in range(40):
        h, w = rng.integers(1, 30, size=2)
        grid = rng.random((h, w)) < rng.random() * 0.6
        goals = np.argwhere(np.ones((h, w)))[rng.integers(0, h * w, 4)]  # obstacles too
        flat = shortest_path(_adjacency(grid), method="D", unweighted=True,
                             indices=goals[:, 0] * w + goals[:, 1])
        expected = np.where(np.isinf(flat), -1, flat).astype(np.int32).reshape(-1, h, w)
        expected[grid[goals[:, 0], goals[:, 1]]] = -1
        np.testing.assert_array_equal(bfs_distances_many(grid, goals), expected,
                                      err_msg=f"trial {trial}")


def test_a_repeated_search_gives_the_same_distances_and_the_caller_owns_them():
    from mapf_fleet.grid.heuristic import bfs_distances

    grid = generate_instance(24, 2, 0.3, 5).grid
    goal = tuple(np.argwhere(grid == 0)[0])
    first = bfs_distances(grid, goal)
    expected = first.copy()
    first[:] = 7  # the map's kept searches are not the caller's array
    np.testing.assert_array_equal(bfs_distances(grid, goal), expected)
