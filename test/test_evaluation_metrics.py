"""Metrics of hand-made episodes, checked against values worked out by hand."""

import math

import numpy as np
import pytest

from mapf_fleet.evaluation.metrics import EpisodeTracker, episode_from_trajectory, summarize


def test_success_two_agents_with_a_collision():
    # Agent 0: (0,0) -> (0,1) -> (0,2) goal at step 2. Agent 1: goal (1,0), its move at step 1 is
    # reverted (stays at (1,1)), it arrives at step 3. All on goal at step 3.
    goals = np.array([[0, 2], [1, 0]])
    positions = np.array([
        [[0, 0], [1, 1]],
        [[0, 1], [1, 1]],
        [[0, 2], [1, 1]],
        [[0, 2], [1, 0]],
    ])
    collided = np.array([[False, True], [False, False], [False, False]])
    rec = episode_from_trajectory(positions, goals, collided, max_steps=10, lower_bound=2)
    assert rec.success
    assert rec.steps == 3
    assert rec.sum_of_costs == 2 + 3
    assert rec.makespan == 3
    assert rec.collisions == 1
    assert rec.agent_success == 1.0
    assert rec.lower_bound_ratio == pytest.approx(1.5)


def test_failure_counts_the_limit_and_last_arrival():
    # Agent 0 reaches its goal at step 1, leaves at 2, comes back at 3: its cost is 3 (last
    # arrival). Agent 1 never arrives: its cost is the limit.
    goals = np.array([[0, 1], [2, 2]])
    positions = np.array([
        [[0, 0], [2, 0]],
        [[0, 1], [2, 0]],
        [[0, 0], [2, 0]],
        [[0, 1], [2, 0]],
        [[0, 1], [2, 0]],
    ])
    collided = np.zeros((4, 2), dtype=bool)
    collided[1:, 1] = True  # agent 1 bumps three times
    rec = episode_from_trajectory(positions, goals, collided, max_steps=4, lower_bound=2)
    assert not rec.success
    assert rec.steps == 4  # the limit, as the paper counts failures
    assert rec.sum_of_costs == 3 + 4
    assert rec.makespan == 4
    assert rec.collisions == 3
    assert rec.agents_on_goal == 1 and rec.agent_success == 0.5
    assert rec.lower_bound_ratio == pytest.approx(2.0)


def test_agent_starting_on_goal_costs_nothing():
    goals = np.array([[0, 0], [0, 2]])
    positions = np.array([[[0, 0], [0, 1]], [[0, 0], [0, 2]]])
    rec = episode_from_trajectory(positions, goals, np.zeros((1, 2), bool), max_steps=5, lower_bound=1)
    assert rec.success and rec.steps == 1
    assert rec.sum_of_costs == 0 + 1


def test_tracker_refuses_steps_after_the_end():
    tracker = EpisodeTracker(np.array([[0, 0]]), np.array([[0, 1]]), max_steps=1, lower_bound=1)
    tracker.update(np.array([[0, 0]]), np.array([True]))
    assert tracker.done and not tracker.success
    with pytest.raises(RuntimeError):
        tracker.update(np.array([[0, 1]]), np.array([False]))


def test_trajectory_shape_mismatch_is_reported():
    with pytest.raises(ValueError, match="collided"):
        episode_from_trajectory(np.zeros((3, 1, 2)), np.zeros((1, 2)), np.zeros((1, 1)), 5, 1)


def test_summary_is_the_paper_average():
    goals = np.array([[0, 1]])
    solved = episode_from_trajectory(np.array([[[0, 0]], [[0, 1]]]), goals, np.zeros((1, 1), bool), 10, 1)
    failed = episode_from_trajectory(
        np.array([[[0, 0]]] * 11), goals, np.ones((10, 1), bool), 10, 1
    )
    s = summarize([solved, failed])
    assert s.episodes == 2
    assert s.success_rate == 0.5
    assert s.average_steps == pytest.approx((1 + 10) / 2)
    assert s.collisions == pytest.approx(5.0)
    assert s.lower_bound_ratio == pytest.approx(5.5)
    assert s.lower_bound_ratio_solved == pytest.approx(1.0)
    only_failed = summarize([failed])
    assert math.isnan(only_failed.lower_bound_ratio_solved)
    assert only_failed.to_dict()["lower_bound_ratio_solved"] is None
    with pytest.raises(ValueError):
        summarize([])


def test_stalled_agents_and_deadlocks_at_the_end():
    """Agents 0 and 1 face each other in a corridor and wait from step 1 to the limit (a
    deadlock: stalled beside another agent); agent 2 waits alone; agent 3 moves until the end
    (not stalled); agent 4 waits on its goal (not counted)."""
    from mapf_fleet.evaluation.metrics import STALL_STEPS

    limit = STALL_STEPS + 5
    goals = np.array([[0, 9], [0, 0], [5, 5], [9, 9], [7, 0]])
    start = np.array([[0, 3], [0, 4], [5, 0], [9, 0], [7, 0]])
    positions = [start]
    for t in range(1, limit + 1):
        now = start.copy()
        now[2] = [5, 1] if t >= 4 else [5, 0]  # moves once at step 4, then waits alone
        now[3] = [9, t % 2]  # oscillates to the end
        positions.append(now)
    rec = episode_from_trajectory(np.stack(positions), goals, np.zeros((limit, 5), bool), limit, 9)
    assert not rec.success
    assert rec.stalled_agents == 3 and rec.stalled_beside_agent == 2
    # an agent that moved within the last STALL_STEPS steps is not stalled
    short = episode_from_trajectory(np.stack(positions[:STALL_STEPS]), goals,
                                    np.zeros((STALL_STEPS - 1, 5), bool), STALL_STEPS - 1, 9)
    assert short.stalled_agents == 0
