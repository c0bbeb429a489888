"""LearnedPolicy (state carried between calls, exploration) and the step in training mode."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mapf_fleet.models import DCCNetwork, DHCNetwork, LearnedPolicy, ModelConfig
from mapf_fleet.models.synthetic import make_sensitive, random_positions, synthetic_obs


def fleet(seed, envs=2, agents=10, side=7):
    rng = np.random.default_rng(seed)
    positions = np.stack([random_positions(rng, agents, side) for _ in range(envs)])
    obs = np.stack([synthetic_obs(rng, p) for p in positions])
    return obs, positions


def network(algo, seed=0):
    config = ModelConfig.preset(algo, "small")
    net = DHCNetwork(config) if algo == "dhc" else DCCNetwork(config)
    return make_sensitive(net, seed).eval()


@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_policy_carries_hidden_and_last_actions_like_a_manual_step_chain(algo):
    net = network(algo)
    policy = LearnedPolicy(net, device="cpu")
    policy.reset(2, 10)
    hidden, last = None, None
    for seed in range(3):
        obs, positions = fleet(seed)
        actions = policy.act(obs, positions)
        with torch.no_grad():
            extra = {"last_action": last} if algo == "dcc" else {}
            out = net.step(torch.from_numpy(obs), torch.from_numpy(positions), hidden, **extra)
        hidden, last = out.hidden, out.actions
        assert actions.shape == (2, 10) and actions.dtype == np.int64
        np.testing.assert_array_equal(actions, out.actions.numpy())
        np.testing.assert_allclose(policy.q_values, out.q.numpy(), atol=1e-6)
    assert torch.count_nonzero(policy.hidden) > 0


def test_hidden_state_changes_the_decision_so_reset_matters():
    net = network("dhc")
    policy = LearnedPolicy(net, device="cpu")
    obs, positions = fleet(0, envs=1)
    policy.act(obs, positions)
    first = policy.q_values.copy()
    policy.act(obs, positions)
    assert not np.allclose(policy.q_values, first)  # same input, carried hidden differs
    policy.reset(1, 10)
    policy.act(obs, positions)
    np.testing.assert_allclose(policy.q_values, first, atol=1e-6)


def test_reset_env_only_clears_that_environment():
    policy = LearnedPolicy(network("dcc"), device="cpu")
    obs, positions = fleet(1)
    policy.reset(2, 10)
    policy.act(obs, positions)
    kept = policy.hidden[1].clone()
    policy.reset_env(0)
    assert torch.count_nonzero(policy.hidden[0]) == 0 and (policy.last_actions[0] == -1).all()
    assert torch.equal(policy.hidden[1], kept)


def test_single_episode_without_batch_axis_and_shape_errors():
    policy = LearnedPolicy(network("dhc"), device="auto")
    obs, positions = fleet(2, envs=1)
    assert policy.act(obs[0], positions[0]).shape == (10,)
    with pytest.raises(ValueError, match="reset for 1 x 10"):
        policy.act(obs[:, :5], positions[:, :5])


def test_epsilon_greedy_explores_with_the_given_rng():
    policy = LearnedPolicy(network("dhc"), device="cpu")
    obs, positions = fleet(3, envs=4, agents=16, side=30)
    policy.reset(4, 16)
    greedy = policy.act(obs, positions)
    policy.reset(4, 16)
    same = policy.act(obs, positions, greedy=False, epsilon=0.0, rng=np.random.default_rng(0))
    np.testing.assert_array_equal(same, greedy)
    policy.reset(4, 16)
    explored = policy.act(obs, positions, greedy=False, epsilon=1.0, rng=np.random.default_rng(0))
    assert (explored != greedy).mean() > 0.5  # random actions: about 4/5 differ
    policy.reset(4, 16)
    # Per-agent epsilon: agent 0 explores, the others act greedily.
    eps = np.zeros((4, 16))
    eps[:, 0] = 1.0
    partial = policy.act(obs, positions, greedy=False, epsilon=eps, rng=np.random.default_rng(1))
    np.testing.assert_array_equal(partial[:, 1:], greedy[:, 1:])
    with pytest.raises(ValueError, match="epsilon"):
        policy.act(obs, positions, greedy=False, epsilon=2.0)


# ---- training mode ---------------------------------------------------------------------------


@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_gradients_reach_encoder_communication_and_head(algo):
    net = network(algo).train()
    obs, positions = fleet(4, envs=2, agents=12, side=6)
    hidden, last = None, None
    loss = 0.0
    for _ in range(2):  # a short sequence, hidden carried with gradients
        extra = {"last_action": last} if algo == "dcc" else {}
        out = net.step(torch.from_numpy(obs), torch.from_numpy(positions), hidden, **extra)
        hidden, last = out.hidden, out.actions.detach()
        loss = loss + out.q.pow(2).mean()
    assert out.comm_mask.any()
    loss.backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_dcc_replayed_comm_mask_gives_the_same_step():
    net = network("dcc")
    obs, positions = fleet(5, envs=2, agents=12, side=6)
    last = torch.randint(-1, 5, (2, 12))
    hidden = torch.randn(2, 12, net.config.hidden_dim) * 0.3
    with torch.no_grad():
        computed = net.step(obs, positions, hidden, last)
    replayed = net.step(obs, positions, hidden, last, comm_mask=computed.comm_mask)
    assert computed.comm_mask.any()
    np.testing.assert_allclose(replayed.q.detach().numpy(), computed.q.numpy(), atol=1e-5)
    # A different mask changes the result: the replayed mask is really used.
    other = net.step(obs, positions, hidden, last, comm_mask=torch.zeros_like(computed.comm_mask))
    assert not torch.allclose(other.q, computed.q, atol=1e-4)


def test_bad_shapes_name_the_argument():
    net = network("dcc")
    obs, positions = fleet(6)
    with pytest.raises(ValueError, match="positions"):
        net.step(obs, positions[:, :5])
    with pytest.raises(ValueError, match="obs"):
        net.step(obs[..., :7, :7], positions)
    with pytest.raises(ValueError, match="last_action"):
        net.step(obs, positions, last_action=np.zeros((2, 3), dtype=np.int64))


def test_inference_batches_are_padded_to_few_shapes_with_the_same_numbers():
    """Without autograd DCC encodes its rows padded to `padded_rows` (a bounded set of shapes,
    so oneDNN's per-shape kernels stop piling up in a long-running fleet); the rows themselves
    are encoded as without padding."""
    from mapf_fleet.models.common import padded_rows

    sizes = {padded_rows(n) for n in range(1, 20000)}
    assert len(sizes) <= 8 * 15
    for n in range(1, 5000):
        assert n <= padded_rows(n) <= n + n // 8 and (n >= 16 or padded_rows(n) == n)
    torch.manual_seed(0)
    model = DCCNetwork(ModelConfig.preset("dcc", "small")).eval()
    c, fov = model.config.obs_shape[0], model.config.fov
    for rows in (5, 17, 37, 130):
        obs = torch.rand(rows, c, fov, fov)
        last = torch.randint(-1, 5, (rows,))
        hidden = torch.rand(rows, model.hidden_dim)
        plain = model.encode_batch(obs, last, hidden)  # autograd on: never padded
        with torch.no_grad():
            padded = model.encode_batch(obs, last, hidden)
        assert padded.shape == plain.shape
        torch.testing.assert_close(padded, plain.detach(), rtol=1e-5, atol=1e-5)
