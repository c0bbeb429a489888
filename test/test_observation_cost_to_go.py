"""The "cost_to_go" observation: the paper's six channels plus the normalised
cost-to-go, built by every environment a model runs in, a network warm-started from a "paper"
checkpoint that acts exactly as it, its checkpoints, and the refusal of unknown values."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mapf_fleet.grid.batch_env import BatchMAPFEnv
from mapf_fleet.grid.env import (COST_TO_GO_CHANNEL, EnvConfig, MAPFEnv, cost_to_go_channel,
                                 observe)
from mapf_fleet.grid.heuristic import HeuristicCache, bfs_distances_many, cached_heuristic_channels
from mapf_fleet.grid.instance import Instance, generate_instance
from mapf_fleet.models.checkpoint import (CheckpointError, build_model, load_checkpoint,
                                          save_checkpoint, with_observation)
from mapf_fleet.models.config import ModelConfig
from mapf_fleet.models.policy import LearnedPolicy
from mapf_fleet.models.synthetic import make_sensitive
from mapf_fleet.training.replay import pack_cost_to_go, pack_obs, unpack_obs

META = {"alpha": 0.0, "curriculum": {}, "learner_steps": 0, "training_config": {}}


def _ctg(grid, positions, goals, radius):
    grid, goals = np.asarray(grid, np.uint8), np.asarray(goals)
    obs = observe(grid, np.asarray(positions), goals, cached_heuristic_channels(grid, goals),
                  radius, distances=bfs_distances_many(grid, goals))
    return obs[:, COST_TO_GO_CHANNEL]


def test_channel_values_on_a_hand_made_grid():
    # goal G at (0, 2), the agent A at (2, 2) (6 steps from G, around the wall # of row 1):
    #   . . G . . .
    #   . # # # . .
    #   . . A . . .
    #   . . . . . .
    #   . . . . . .
    grid = np.zeros((5, 6), np.uint8)
    grid[1, 1:4] = 1
    ctg = _ctg(grid, [[2, 2]], [[0, 2]], radius=2)[0]
    # d(cell) - d(A) over the 5x5 FOV, clipped to +-5 (2r+1); the wall holds 5 (blocked)
    steps = np.array([[-4, -5, -5, -5, -4],   # G's row: d 2 1 0 1 2 (0 - 6 clips to -5)
                      [-3, 5, 5, 5, -3],
                      [-2, -1, 0, -1, -2],    # A's row: A itself is 0
                      [-1, 0, 1, 0, -1],
                      [0, 1, 2, 1, 0]])
    np.testing.assert_array_equal(ctg, steps.astype(np.float32) / 5)
    assert ctg.min() == -1.0 and ctg.max() == 1.0
    # off the map and cut off from the goal are blocked too (1.0): A at (1, 0) of a 3x3 map
    # whose middle column is a wall, so its right column cannot reach the goal at (0, 0)
    walled = np.zeros((3, 3), np.uint8)
    walled[:, 1] = 1
    ctg = _ctg(walled, [[1, 0]], [[0, 0]], radius=2)[0]
    blocked = [5, 5, 5, 5, 5]
    np.testing.assert_array_equal(ctg, np.array([blocked, [5, 5, -1, 5, 5], [5, 5, 0, 5, 5],
                                                 [5, 5, 1, 5, 5], blocked], np.float32) / 5)


def test_every_environment_builds_the_same_channel():
    config = EnvConfig(observation="cost_to_go")
    instances = [generate_instance(11, 6, 0.25, seed) for seed in (1, 2)]
    batch = BatchMAPFEnv(instances, config, heuristic_cache=HeuristicCache())
    envs = [MAPFEnv(inst, config) for inst in instances]
    paper = [MAPFEnv(inst) for inst in instances]
    obs = batch.reset()
    rng = np.random.default_rng(0)
    for t in range(6):
        singles = np.stack([env.observe() for env in envs])
        assert singles.shape == (2, 6, 7, 9, 9)
        np.testing.assert_array_equal(obs, singles)
        # the paper's channels are unchanged, the new one is observe()'s with BFS distances
        np.testing.assert_array_equal(singles[:, :, :6], np.stack([p.observe() for p in paper]))
        for k, env in enumerate(envs):
            np.testing.assert_array_equal(
                singles[k, :, COST_TO_GO_CHANNEL],
                _ctg(env.grid, env.positions, env.goals, 4))
        actions = rng.integers(0, 5, size=(2, 6))
        obs, *_ = batch.step(actions)
        for k in range(2):
            envs[k].step(actions[k])
            paper[k].step(actions[k])


def test_new_goals_give_a_new_channel():
    """Goals given at run time (lifelong, the fleet): the channel follows the goals, from the
    cache the heuristic bits use (keyed by map and goal)."""
    inst = generate_instance(12, 4, 0.2, 3)
    env = MAPFEnv(inst, EnvConfig(observation="cost_to_go"))
    moved = Instance(inst.grid, inst.starts, inst.goals[::-1].copy())
    obs = env.reset(moved)
    np.testing.assert_array_equal(obs[:, COST_TO_GO_CHANNEL],
                                  _ctg(inst.grid, inst.starts, moved.goals, 4))
    assert not np.array_equal(obs, MAPFEnv(inst, EnvConfig(observation="cost_to_go")).reset())


def test_shard_storage_is_exact():
    env = MAPFEnv(generate_instance(10, 5, 0.3, 4), EnvConfig(observation="cost_to_go"))
    obs = env.reset()
    ctg = pack_cost_to_go(obs)
    assert ctg.dtype == np.int8 and ctg.shape == (5, 9, 9)
    np.testing.assert_array_equal(unpack_obs(pack_obs(obs), ctg), obs)
    np.testing.assert_array_equal(unpack_obs(pack_obs(obs)), obs[:, :6])
    np.testing.assert_array_equal(cost_to_go_channel(ctg, 4), obs[:, COST_TO_GO_CHANNEL])


@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_warm_start_acts_exactly_as_the_paper_model(algo):
    torch.manual_seed(0)
    paper = build_model(ModelConfig.preset(algo, "small")).eval()
    if algo == "dcc":
        make_sensitive(paper, seed=3)  # DCC's causal sets non-empty: its messages count too
    warm = with_observation(paper, "cost_to_go").eval()
    assert warm.config.observation == "cost_to_go" and warm.config.obs_shape == (7, 9, 9)
    first = warm.obs_encoder[0].weight
    assert first.shape[1] == 7 and (first[:, 6] == 0).all()
    assert torch.equal(first[:, :6], paper.obs_encoder[0].weight)
    assert with_observation(warm, "cost_to_go") is warm
    with pytest.raises(ValueError, match="cannot drop"):
        with_observation(warm, "paper")
    instance = generate_instance(10, 8, 0.2, 5)
    env_paper, env_ctg = MAPFEnv(instance), MAPFEnv(instance, EnvConfig(observation="cost_to_go"))
    a, b = LearnedPolicy(paper, "cpu"), LearnedPolicy(warm, "cpu")
    obs_paper, obs_ctg = env_paper.reset(), env_ctg.reset()
    for _ in range(8):
        actions = a.act(obs_paper, env_paper.positions)
        assert np.array_equal(b.act(obs_ctg, env_ctg.positions), actions)
        assert np.array_equal(a.q_values, b.q_values)  # the same numbers, not just the argmax
        assert np.array_equal(a.comm_mask, b.comm_mask)
        obs_paper, *_ = env_paper.step(actions)
        obs_ctg, *_ = env_ctg.step(actions)
    # the paper's observation is refused with the reason, not a shape error deep in the network
    with pytest.raises(ValueError, match="cost_to_go.*7 channels.*EnvConfig"):
        b.act(obs_paper, env_paper.positions)


def test_checkpoint_round_trip_and_old_files(tmp_path):
    torch.manual_seed(1)
    model = with_observation(build_model(ModelConfig.preset("dhc", "small")), "cost_to_go")
    path = save_checkpoint(tmp_path / "ctg.pt", model, META)
    loaded, meta = load_checkpoint(path)
    assert meta["model_config"]["observation"] == "cost_to_go"
    assert loaded.config == model.config
    for (name, x), (_, y) in zip(model.state_dict().items(), loaded.state_dict().items()):
        assert torch.equal(x, y), name
    # a file written before the field existed loads as "paper", unchanged
    paper = build_model(ModelConfig.preset("dcc", "small"))
    old = save_checkpoint(tmp_path / "old.pt", paper, META)
    payload = torch.load(old, weights_only=True)
    del payload["metadata"]["model_config"]["observation"]
    torch.save(payload, old)
    loaded, meta = load_checkpoint(old)
    assert "observation" not in meta["model_config"]
    assert loaded.config.observation == "paper" and loaded.config == paper.config


def test_an_unknown_observation_is_refused_naming_file_field_and_value(tmp_path):
    from mapf_fleet.evaluation.policies import PolicySpec, build_policy

    path = save_checkpoint(tmp_path / "foo.pt", build_model(ModelConfig.preset("dhc", "small")),
                           META)
    payload = torch.load(path, weights_only=True)
    payload["metadata"]["model_config"]["observation"] = "foo"
    torch.save(payload, path)
    pattern = r"foo\.pt: field metadata\.model_config: ModelConfig\.observation.*'foo'"
    with pytest.raises(CheckpointError, match=pattern):
        load_checkpoint(path)
    # the evaluator (and the policy nodes, which load the same way) refuse it too
    with pytest.raises(CheckpointError, match=pattern):
        build_policy(PolicySpec("checkpoint", "foo", path=str(path)))


def test_the_evaluator_runs_a_cost_to_go_checkpoint(tmp_path):
    """The runner builds what the policy reads: the warm-started checkpoint plays the paper
    checkpoint's episodes, move for move."""
    from mapf_fleet.evaluation.policies import PolicySpec, build_policy
    from mapf_fleet.evaluation.protocol import InstanceSet
    from mapf_fleet.evaluation.runner import run_decentralized

    torch.manual_seed(2)
    paper = build_model(ModelConfig.preset("dhc", "small"))
    paths = {"paper": save_checkpoint(tmp_path / "paper.pt", paper, META),
             "ctg": save_checkpoint(tmp_path / "ctg.pt", with_observation(paper, "cost_to_go"),
                                    META)}
    instances = InstanceSet.from_instances([generate_instance(10, 5, 0.2, s) for s in (6, 7)],
                                           "test")
    records = {}
    for name, path in paths.items():
        policy = build_policy(PolicySpec("checkpoint", name, path=str(path)))
        assert policy.observation == ("cost_to_go" if name == "ctg" else "paper")
        records[name] = run_decentralized(policy, instances, 24, conflict_rule="pibt_anchor")
    assert records["ctg"] == records["paper"]


def test_the_ape_x_trainer_refuses_the_option():
    from mapf_fleet.training.config import TrainConfigError, config_from_dict

    with pytest.raises(TrainConfigError, match="model_overrides.*paper's observation only"):
        config_from_dict({"preset": "dcc", "model_overrides": {"observation": "cost_to_go"}})
