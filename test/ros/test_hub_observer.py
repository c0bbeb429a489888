"""The hub's cached observation of its local robots equals the grid world's `observe`."""

from __future__ import annotations

import numpy as np

from mapf_fleet.grid.env import observe
from mapf_fleet.grid.heuristic import bfs_distances_many, cached_heuristic_channels
from mapf_fleet.grid.instance import generate_instance
from mapf_fleet.ros.hub import LocalObserver


def test_local_observer_equals_observe_for_a_subset_of_robots():
    instance = generate_instance(12, 10, 0.3, 4)
    grid, goals = np.asarray(instance.grid), np.asarray(instance.goals)
    positions = np.asarray(instance.starts)
    local = np.array([7, 2, 9])  # any order: rows follow `local`
    expected = observe(grid, positions, goals, cached_heuristic_channels(grid, goals), 4)[local]
    observer = LocalObserver(grid, goals[local], 4)
    np.testing.assert_array_equal(observer.observe(positions, local), expected)
    # robots near the border see off-map cells as obstacles, and others in channel 0
    assert expected[:, 0].sum() > 0


def test_cost_to_go_observation_follows_the_goals():
    """A model reading "cost_to_go" gets observe()'s 7th channel; goals given at run time make
    the hub build a new observer (its key), whose distances are the new goals'."""
    instance = generate_instance(12, 10, 0.3, 5)
    grid, positions = np.asarray(instance.grid), np.asarray(instance.starts)
    local = np.array([3, 8, 0])
    for goals in (np.asarray(instance.goals), np.asarray(instance.goals)[::-1].copy()):
        expected = observe(grid, positions, goals, cached_heuristic_channels(grid, goals), 4,
                           distances=bfs_distances_many(grid, goals))[local]
        observer = LocalObserver(grid, goals[local], 4, "cost_to_go")
        assert observer.observe(positions, local).shape == (3, 7, 9, 9)
        np.testing.assert_array_equal(observer.observe(positions, local), expected)
