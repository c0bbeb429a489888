"""BatchMAPFEnv equals independent MAPFEnv episodes."""

import numpy as np
import pytest

from mapf_fleet.grid.batch_env import BatchMAPFEnv
from mapf_fleet.grid.env import EnvConfig, MAPFEnv
from mapf_fleet.grid.instance import generate_instance
from mapf_fleet.grid.policies import heuristic_policy


@pytest.mark.parametrize("finish", ["team", "per_agent"])
def test_batch_matches_single_envs(finish):
    config = EnvConfig(max_steps=30, finish_reward=finish)
    instances = [generate_instance(10, 6, 0.2, seed) for seed in range(5)]
    batch = BatchMAPFEnv(instances, config)
    singles = [MAPFEnv(inst, config) for inst in instances]
    obs = batch.reset()
    single_obs = [env.reset() for env in singles]
    rng = np.random.default_rng(0)
    finished = [False] * 5
    for _ in range(40):
        np.testing.assert_array_equal(obs, np.stack(single_obs))
        # mix random and heuristic actions so some episodes succeed early
        actions = np.where(rng.random((5, 6)) < 0.3, rng.integers(0, 5, (5, 6)),
                           heuristic_policy(obs))
        obs, rewards, done, info = batch.step(actions)
        for b, env in enumerate(singles):
            if finished[b]:
                assert done[b] and (rewards[b] == 0).all()
                single_obs[b] = env.observe()
                continue
            o, r, d, i = env.step(actions[b])
            single_obs[b] = o
            np.testing.assert_array_equal(rewards[b], r)
            assert done[b] == d and info["success"][b] == i["success"]
            assert info["steps"][b] == i["steps"]
            np.testing.assert_array_equal(info["collisions"][b], i["collisions"])
            np.testing.assert_array_equal(batch.positions[b], env.positions)
            finished[b] = d
        if done.all():
            break
    assert any(info["success"]) and done.all()


def test_batch_rejects_mixed_sizes():
    with pytest.raises(ValueError, match=r"instances\[1\] is 12x12 with 4 agents"):
        BatchMAPFEnv([generate_instance(10, 4, 0.2, 0), generate_instance(12, 4, 0.2, 0)])


def test_batch_agents_on_adjacent_maps_do_not_interact():
    # agent at the right edge of map 0 moving right must hit the edge, not map 1
    from mapf_fleet.grid.instance import Instance
    grid = np.zeros((3, 3), np.uint8)
    a = Instance(grid, np.array([[1, 2]]), np.array([[0, 0]]))
    b = Instance(grid, np.array([[1, 0]]), np.array([[2, 2]]))
    env = BatchMAPFEnv([a, b])
    obs, rewards, _, info = env.step(np.array([[4], [3]]))
    assert info["collisions"].tolist() == [[True], [True]]
    assert obs[0, 0, 0].sum() == 0 and obs[0, 0, 1, 4, 5:].sum() == 4   # sees edge, not map 1
