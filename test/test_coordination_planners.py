"""The classical reference: plans are valid in our environment and regions are planned apart."""

import numpy as np
import pytest

pytest.importorskip("pymapf")

from mapf_fleet.coordination.planners import ClassicalPlanner, positions_to_actions
from mapf_fleet.evaluation.protocol import InstanceSet
from mapf_fleet.evaluation.runner import lower_bounds, replay_plan
from mapf_fleet.grid.instance import generate_instance


def test_positions_to_actions_uses_dhc_order():
    positions = np.array([[[2, 2]], [[1, 2]], [[2, 2]], [[2, 1]], [[2, 2]], [[2, 2]]])
    assert positions_to_actions(positions)[:, 0].tolist() == [1, 2, 3, 4, 0]
    with pytest.raises(ValueError, match="agent 0"):
        positions_to_actions(np.array([[[0, 0]], [[1, 1]]]))


@pytest.mark.parametrize("algorithm", ["lacam", "pibt"])
def test_plan_replays_without_collisions(algorithm):
    inst = generate_instance(16, 12, 0.2, np.random.default_rng(5))
    result = ClassicalPlanner(algorithm, time_limit=5.0).plan(inst.grid, inst.starts, inst.goals)
    assert result.complete, result.reason
    assert np.array_equal(result.positions[0], inst.starts)
    assert np.array_equal(result.positions[-1], inst.goals)
    instances = InstanceSet.from_instances([inst], "test")
    record = replay_plan(positions_to_actions(result.positions), instances, 0, 256, lower_bounds(instances)[0])
    assert record.success
    assert record.collisions == 0
    assert record.steps == len(result.positions) - 1
    assert record.steps >= record.lower_bound


def test_precomputed_distances_give_the_same_plan():
    inst = generate_instance(20, 16, 0.3, np.random.default_rng(2))
    fast = ClassicalPlanner("lacam", 5.0, fast_distances=True).plan(inst.grid, inst.starts, inst.goals)
    slow = ClassicalPlanner("lacam", 5.0, fast_distances=False).plan(inst.grid, inst.starts, inst.goals)
    assert np.array_equal(fast.positions, slow.positions)


def test_unsolvable_region_keeps_its_agents_and_spares_the_others():
    # Row 0 is a dead-end corridor cut off by a wall: two agents must swap there (impossible).
    # The open area below holds one agent that can reach its goal.
    grid = np.zeros((4, 5), dtype=np.uint8)
    grid[1, :] = 1
    starts = np.array([[0, 0], [0, 1], [3, 0]])
    goals = np.array([[0, 1], [0, 0], [3, 4]])
    result = ClassicalPlanner("lacam", time_limit=2.0).plan(grid, starts, goals)
    assert not result.complete and result.unsolved_agents == 2
    assert np.array_equal(result.positions[:, :2], np.repeat(starts[None, :2], len(result.positions), 0))
    assert tuple(result.positions[-1, 2]) == (3, 4)


def test_bad_planner_settings_are_refused():
    with pytest.raises(ValueError, match="algorithm"):
        ClassicalPlanner("cbs")
    with pytest.raises(ValueError, match="time_limit"):
        ClassicalPlanner("lacam", time_limit=0)
