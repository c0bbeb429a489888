"""Rewards, finish modes, episode ends, observations and the cooperative reward (Eq. 2)."""

import numpy as np
import pytest

from mapf_fleet.grid.actions import DOWN, LEFT, RIGHT, STAY, UP
from mapf_fleet.grid.env import EnvConfig, MAPFEnv, observe
from mapf_fleet.grid.heuristic import bfs_distances, heuristic_channels
from mapf_fleet.grid.instance import Instance, generate_instance
from mapf_fleet.grid.policies import heuristic_policy
from mapf_fleet.grid.reward import CooperativeReward, fov_neighbours


def make_env(starts, goals, grid=None, size=5, **config):
    grid = np.zeros((size, size), np.uint8) if grid is None else np.asarray(grid, np.uint8)
    return MAPFEnv(Instance(grid, np.array(starts), np.array(goals)), EnvConfig(**config))


# --- rewards ----------------------------------------------------------------------------------

def test_step_rewards_by_kind():
    # 0 moves freely, 1 stays off goal, 2 stays on goal, 3 bumps the map edge
    env = make_env([(2, 2), (0, 4), (4, 4), (0, 0)], [(0, 2), (1, 4), (4, 4), (4, 0)])
    _, rewards, done, info = env.step(np.array([UP, STAY, STAY, UP]))
    np.testing.assert_allclose(rewards, [-0.075, -0.075, 0.0, -0.5])
    assert rewards.dtype == np.float32
    assert not done and info["steps"] == 1 and not info["success"]
    assert info["collisions"].tolist() == [False, False, False, True]
    assert info["on_goal"].tolist() == [False, False, True, False]


def test_swap_collision_rewards():
    env = make_env([(2, 1), (2, 2)], [(0, 0), (4, 4)])
    _, rewards, _, info = env.step(np.array([RIGHT, LEFT]))
    np.testing.assert_allclose(rewards, [-0.5, -0.5])
    assert env.positions.tolist() == [[2, 1], [2, 2]]


def test_team_finish_reward_replaces_step_rewards():
    env = make_env([(2, 1), (0, 0)], [(2, 2), (0, 0)])
    _, rewards, done, info = env.step(np.array([RIGHT, STAY]))
    np.testing.assert_allclose(rewards, [3.0, 3.0])
    assert done and info["success"] and info["on_goal"].all()
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.array([STAY, STAY]))


def test_team_mode_no_bonus_until_all_on_goal():
    env = make_env([(2, 1), (0, 0)], [(2, 2), (4, 4)])
    _, rewards, done, _ = env.step(np.array([RIGHT, STAY]))
    np.testing.assert_allclose(rewards, [-0.075, -0.075])
    assert not done


def test_per_agent_finish_reward_first_arrival_only():
    env = make_env([(2, 1), (0, 0)], [(2, 2), (0, 2)], finish_reward="per_agent")
    _, rewards, done, _ = env.step(np.array([RIGHT, RIGHT]))
    np.testing.assert_allclose(rewards, [3.0, -0.075])
    assert not done
    _, rewards, _, _ = env.step(np.array([RIGHT, STAY]))       # 0 leaves its goal
    np.testing.assert_allclose(rewards, [-0.075, -0.075])
    _, rewards, _, _ = env.step(np.array([LEFT, STAY]))        # 0 returns: no second bonus
    np.testing.assert_allclose(rewards, [-0.075, -0.075])
    _, rewards, done, info = env.step(np.array([STAY, RIGHT]))  # 1 arrives, all on goal
    np.testing.assert_allclose(rewards, [0.0, 3.0])
    assert done and info["success"]


def test_episode_ends_at_max_steps_without_success():
    env = make_env([(0, 0)], [(4, 4)], max_steps=3)
    for k in range(3):
        _, _, done, info = env.step(np.array([STAY]))
    assert done and not info["success"] and info["steps"] == 3


def test_reset_restores_start_and_last_actions():
    env = make_env([(0, 0), (4, 4)], [(0, 4), (4, 0)])
    assert env.last_actions.tolist() == [-1, -1]
    assert not env.last_action_one_hot().any()
    env.step(np.array([RIGHT, LEFT]))
    assert env.last_actions.tolist() == [RIGHT, LEFT]
    assert env.last_action_one_hot()[0].tolist() == [0, 0, 0, 0, 1]
    obs = env.reset()
    assert env.positions.tolist() == [[0, 0], [4, 4]] and env.steps == 0
    np.testing.assert_array_equal(obs, env.observe())


def test_env_config_validation():
    with pytest.raises(ValueError, match="finish_reward"):
        EnvConfig(finish_reward="everyone")
    with pytest.raises(ValueError, match="max_steps"):
        EnvConfig(max_steps=0)
    with pytest.raises(ValueError, match="reward_collision"):
        EnvConfig(reward_collision=float("nan"))


# --- observations -----------------------------------------------------------------------------

GRID = np.array([[0, 0, 0, 0, 0],
                 [0, 1, 1, 0, 0],
                 [0, 0, 0, 1, 0],
                 [0, 0, 0, 0, 0]], np.uint8)


def naive_window(values, centre, radius, fill):
    h, w = values.shape
    out = np.full((2 * radius + 1, 2 * radius + 1), fill, values.dtype)
    for dr in range(-radius, radius + 1):
        for dc in range(-radius, radius + 1):
            r, c = centre[0] + dr, centre[1] + dc
            if 0 <= r < h and 0 <= c < w:
                out[dr + radius, dc + radius] = values[r, c]
    return out


def test_heuristic_channels_by_hand():
    # goal (0, 4); (0, 3) one step away; (1, 3) reaches it by going up; (1, 4) by going up
    ch = heuristic_channels(GRID, (0, 4))
    assert ch.shape == (4, 4, 5) and ch.dtype == np.uint8
    up, down, left, right = ch
    assert right[0, 3] == 1 and up[0, 3] == 0 and down[0, 3] == 0
    assert up[1, 3] == 1 and right[1, 3] == 1      # both neighbours are 1 step from the goal
    assert up[1, 4] == 1 and left[1, 4] == 0       # (1, 3) is as far as (1, 4)
    assert ch[:, 0, 4].sum() == 0                   # the goal itself
    assert ch[:, 1, 1].sum() == 0 and ch[:, 2, 3].sum() == 0   # obstacles
    assert up[1, 0] == 1 and right[2, 0] == 0       # (2, 1) is 7 steps away, (2, 0) only 6
    dist = bfs_distances(GRID, (0, 4))
    assert dist[0, 4] == 0 and dist[3, 0] == 7 and dist[1, 1] == -1
    # every set bit points one step closer, every unset free neighbour does not
    for r in range(4):
        for c in range(5):
            for k, (dr, dc) in enumerate([(-1, 0), (1, 0), (0, -1), (0, 1)]):
                rr, cc = r + dr, c + dc
                closer = (0 <= rr < 4 and 0 <= cc < 5 and dist[r, c] >= 0 and dist[rr, cc] >= 0
                          and dist[rr, cc] == dist[r, c] - 1)
                assert ch[k, r, c] == closer


def test_unreachable_region_has_no_heuristic_bits():
    grid = np.array([[0, 1, 0], [0, 1, 0], [0, 1, 0]], np.uint8)
    dist = bfs_distances(grid, (0, 0))
    assert (dist[:, 2] == -1).all() and dist[2, 0] == 2
    assert heuristic_channels(grid, (0, 0))[:, :, 2].sum() == 0


@pytest.mark.parametrize("radius", [1, 2, 4])
def test_observation_channels_match_naive_windows(radius):
    starts = np.array([[0, 0], [3, 4], [2, 2], [0, 2]])
    goals = np.array([[0, 4], [3, 0], [0, 0], [3, 2]])
    channels = np.stack([heuristic_channels(GRID, g) for g in goals])
    obs = observe(GRID, starts, goals, channels, radius)
    s = 2 * radius + 1
    assert obs.shape == (4, 6, s, s) and obs.dtype == np.float32
    occupancy = np.zeros_like(GRID)
    occupancy[starts[:, 0], starts[:, 1]] = 1
    for i, p in enumerate(starts):
        agents = naive_window(occupancy, p, radius, 0)
        agents[radius, radius] = 0
        np.testing.assert_array_equal(obs[i, 0], agents)
        np.testing.assert_array_equal(obs[i, 1], naive_window(GRID, p, radius, 1))  # off-map = 1
        for k in range(4):
            np.testing.assert_array_equal(obs[i, 2 + k], naive_window(channels[i, k], p, radius, 0))


def test_observation_corner_by_hand():
    starts = np.array([[0, 0], [1, 0]])
    goals = np.array([[3, 4], [0, 4]])
    channels = np.stack([heuristic_channels(GRID, g) for g in goals])
    obs = observe(GRID, starts, goals, channels, 4)
    centre = 4
    assert obs[0, 0, centre, centre] == 0 and obs[0, 0, centre + 1, centre] == 1   # agent 1 below
    assert obs[0, 0].sum() == 1
    assert (obs[0, 1, :centre, :] == 1).all() and (obs[0, 1, :, :centre] == 1).all()  # off-map
    assert obs[0, 1, centre + 1, centre + 1] == 1   # obstacle (1, 1)
    assert obs[0, 1, centre, centre] == 0
    assert (obs[0, 2:, :centre, :] == 0).all()      # heuristic padded 0


def test_env_observation_tracks_moves():
    grid = np.zeros((6, 6), np.uint8)
    inst = Instance(grid, np.array([[2, 2], [2, 3]]), np.array([[5, 5], [0, 0]]))
    env = MAPFEnv(inst)
    env.step(np.array([DOWN, STAY]))
    obs = env.observe()
    channels = np.stack([heuristic_channels(grid, g) for g in inst.goals])
    np.testing.assert_array_equal(obs, observe(grid, env.positions, env.goals, channels, 4))
    assert obs[1, 0, 4 + 1, 4 - 1] == 1 and obs[1, 0].sum() == 1


def test_env_matches_pure_functions_on_random_episode():
    inst = generate_instance(20, 12, 0.3, 5)
    env = MAPFEnv(inst)
    channels = np.stack([heuristic_channels(inst.grid, g) for g in inst.goals])
    rng = np.random.default_rng(0)
    obs = env.reset()
    for _ in range(40):
        np.testing.assert_array_equal(obs, observe(inst.grid, env.positions, env.goals, channels))
        obs, _, done, _ = env.step(rng.integers(0, 5, inst.num_agents))
        if done:
            break


# --- cooperative reward -----------------------------------------------------------------------

def test_fov_neighbours_chebyshev():
    pos = np.array([[0, 0], [4, 4], [0, 5], [9, 9]])
    near = fov_neighbours(pos, 4)
    assert near.tolist() == [[False, True, False, False],
                             [True, False, True, False],
                             [False, True, False, False],
                             [False, False, False, False]]


def test_cooperative_reward_eq2_by_hand():
    pos = np.array([[0, 0], [4, 4], [0, 5], [9, 9]])
    r = np.array([1.0, -0.5, 2.0, -0.075])
    out = CooperativeReward(alpha=0.3)(r, pos)
    expected = [0.7 * 1.0 + 0.3 * (-0.5),
                0.7 * -0.5 + 0.3 * (1.0 + 2.0) / 2,
                0.7 * 2.0 + 0.3 * (-0.5),
                -0.075]                      # no neighbour: own reward
    np.testing.assert_allclose(out, expected, rtol=1e-6)
    np.testing.assert_allclose(CooperativeReward(alpha=0.0)(r, pos), r, rtol=1e-6)
    np.testing.assert_allclose(CooperativeReward(alpha=1.0)(r, pos)[:3], [-0.5, 1.5, -0.5])


def test_cooperative_reward_validation():
    with pytest.raises(ValueError, match="alpha"):
        CooperativeReward(alpha=1.5)


# --- heuristic policy -------------------------------------------------------------------------

def test_heuristic_policy_follows_bits_and_yields():
    obs = np.zeros((3, 6, 9, 9), np.float32)
    obs[0, 2 + 1, 4, 4] = 1                       # down is closer -> DOWN
    obs[1, 2 + 0, 4, 4] = obs[1, 2 + 3, 4, 4] = 1  # up and right closer, up blocked by agent
    obs[1, 0, 3, 4] = 1
    obs[2, 2 + 2, 4, 4] = 1                       # left closer but occupied -> STAY
    obs[2, 0, 4, 3] = 1
    assert heuristic_policy(obs).tolist() == [DOWN, RIGHT, STAY]


def test_heuristic_policy_solves_open_map():
    inst = Instance(np.zeros((8, 8), np.uint8), np.array([[0, 0], [7, 7]]),
                    np.array([[7, 7], [0, 0]]))
    env = MAPFEnv(inst, EnvConfig(max_steps=64))
    obs, done = env.reset(), False
    while not done:
        obs, _, done, info = env.step(heuristic_policy(obs))
    assert info["success"] and info["steps"] >= 14
