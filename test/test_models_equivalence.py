"""Per-robot inference (each robot sees only its own data and received messages) must equal
the batched step: same Q-values within 1e-5 and the same actions, over consecutive steps."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mapf_fleet.grid.actions import ACTION_DELTAS
from mapf_fleet.models import DCCNetwork, DHCNetwork, ModelConfig, dhc_partners, fov_neighbours
from mapf_fleet.models.synthetic import make_sensitive, random_positions, synthetic_obs

TOL = 1e-5
STEPS = 4

# name -> (agents per episode, map side); several episodes are batched with padding.
SCENARIOS = {
    "pair": ([2], 4),
    "dense16": ([16], 7),
    "sparse16": ([16], 30),
    "padded_mix": ([5, 12, 3], 9),
    "dense64": ([64], 14),
    "sparse64": ([64], 40),
}


@pytest.fixture(autouse=True)
def _one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


# ---- robots, one at a time, exchanging only messages ----------------------------------------


def dhc_robots_step(net: DHCNetwork, obs, positions, hidden):
    cfg = net.config
    partners = dhc_partners(positions, cfg.obs_radius, cfg.max_partners)  # same on every robot
    h = [net.encode(obs[i], hidden[i]) for i in range(len(obs))]
    for round_index in range(cfg.comm_rounds):
        published = list(h)  # every robot publishes its vector of this round
        h = [net.comm_round(round_index, published[i],
                            [published[j] for j in partners[i] if j >= 0])
             for i in range(len(obs))]
    q = torch.stack([net.q_values(v) for v in h])
    return q, torch.stack(h), int((partners >= 0).sum())


def dcc_robots_step(net: DCCNetwork, obs, positions, hidden, last_action):
    n = len(obs)
    radius = net.config.obs_radius
    h, requested = [], []
    for i in range(n):
        indices, offsets = fov_neighbours(positions, i, radius)
        h.append(net.encode(obs[i], last_action[i], hidden[i]))
        requested.append(indices[net.causal_set(obs[i], last_action[i], hidden[i], offsets)])
    inbox = [[] for _ in range(n)]  # requests: (requester pos - receiver pos, requester h)
    for i in range(n):
        for j in requested[i]:
            inbox[j].append((positions[i] - positions[j], h[i]))
    h1 = [net.aggregate_requests(h[j], inbox[j]) for j in range(n)]
    h2 = [net.aggregate_replies(h1[i], [(positions[j] - positions[i], h1[j]) for j in requested[i]])
          for i in range(n)]
    q = torch.stack([net.q_values(v) for v in h2])
    mask = np.zeros((n, n), dtype=bool)
    for i in range(n):
        mask[i, requested[i]] = True
    return q, torch.stack(h2), mask


# ---- the comparison ---------------------------------------------------------------------------


def move(positions: np.ndarray, actions: np.ndarray, side: int) -> np.ndarray:
    """Apply actions one agent after the other, skipping moves off the map or onto an agent."""
    positions = positions.copy()
    occupied = {tuple(p) for p in positions}
    for i, action in enumerate(actions):
        target = positions[i] + ACTION_DELTAS[action]
        if (0 <= target).all() and (target < side).all() and tuple(target) not in occupied:
            occupied.discard(tuple(positions[i]))
            occupied.add(tuple(target))
            positions[i] = target
    return positions


def pad(arrays, width, fill=0):
    out = np.full((len(arrays), width) + arrays[0].shape[1:], fill, dtype=arrays[0].dtype)
    for b, a in enumerate(arrays):
        out[b, : len(a)] = a
    return out


def run_equivalence(algo: str, preset: str, scenario: str, seed: int) -> int:
    """Returns how many messages were exchanged (to show the test was not vacuous)."""
    counts, side = SCENARIOS[scenario]
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    config = ModelConfig.preset(algo, preset)
    net = DHCNetwork(config) if algo == "dhc" else DCCNetwork(config)
    make_sensitive(net, seed).eval()
    width = max(counts)
    positions = [random_positions(rng, n, side) for n in counts]
    robot_hidden = [torch.zeros(n, config.hidden_dim) for n in counts]
    robot_last = [np.full(n, -1) for n in counts]
    batch_hidden = torch.zeros(len(counts), width, config.hidden_dim)
    batch_last = torch.full((len(counts), width), -1, dtype=torch.long)
    agent_mask = torch.from_numpy(pad([np.ones(n, bool) for n in counts], width, False))
    messages = 0
    for step in range(STEPS):
        obs = [synthetic_obs(rng, p, config.obs_radius) for p in positions]
        # Padded slots sit at (0, 0), inside the map, so that a broken agent_mask would show
        # up as an extra neighbour.
        batch_pos = pad(positions, width, fill=0)
        with torch.no_grad():
            kwargs = {"last_action": batch_last} if algo == "dcc" else {}
            out = net.step(torch.from_numpy(pad(obs, width)), torch.from_numpy(batch_pos),
                           batch_hidden, agent_mask=agent_mask, **kwargs)
            for b, n in enumerate(counts):
                if algo == "dhc":
                    q, h, sent = dhc_robots_step(net, obs[b], positions[b], robot_hidden[b])
                else:
                    q, h, mask = dcc_robots_step(net, obs[b], positions[b], robot_hidden[b],
                                                 robot_last[b])
                    np.testing.assert_array_equal(out.comm_mask[b, :n, :n].numpy(), mask,
                                                  err_msg=f"causal sets differ at step {step}")
                    sent = int(mask.sum())
                messages += sent
                where = f"{algo}/{preset}/{scenario} seed {seed} step {step} episode {b}"
                np.testing.assert_allclose(q.numpy(), out.q[b, :n].numpy(), atol=TOL, rtol=0,
                                           err_msg=where)
                actions = q.argmax(-1).numpy()
                np.testing.assert_array_equal(actions, out.actions[b, :n].numpy(), err_msg=where)
                robot_hidden[b] = h  # each robot carries its own post-communication hidden
                robot_last[b] = actions
                positions[b] = move(positions[b], actions, side)
        batch_hidden, batch_last = out.hidden, out.actions
    return messages


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("scenario", ["pair", "dense16", "sparse16", "padded_mix", "dense64",
                                      "sparse64"])
@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_small_preset_per_robot_equals_batched(algo, scenario, seed):
    messages = run_equivalence(algo, "small", scenario, seed)
    if scenario.startswith("dense"):
        assert messages > 0, "no communication happened: the test would prove nothing"


@pytest.mark.parametrize("scenario", ["dense16", "padded_mix", "sparse64"])
@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_paper_preset_per_robot_equals_batched(algo, scenario):
    messages = run_equivalence(algo, "paper", scenario, seed=11)
    if scenario.startswith("dense"):
        assert messages > 0


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_paper_preset_dense64_per_robot_equals_batched(algo, seed):
    assert run_equivalence(algo, "paper", "dense64", seed) > 0


def test_dcc_reference_variant_without_self_attention_is_also_equivalent():
    """attend_self=False (the DCC reference's attention over senders only) keeps the paths equal."""
    config = ModelConfig.preset("dcc", "small", attend_self=False)
    net = make_sensitive(DCCNetwork(config), 3).eval()
    rng = np.random.default_rng(3)
    positions = random_positions(rng, 24, 8)
    obs = synthetic_obs(rng, positions)
    hidden = torch.zeros(24, config.hidden_dim)
    with torch.no_grad():
        out = net.step(torch.from_numpy(obs)[None], torch.from_numpy(positions)[None])
        q, _, mask = dcc_robots_step(net, obs, positions, hidden, np.full(24, -1))
    assert mask.any()
    np.testing.assert_allclose(q.numpy(), out.q[0].numpy(), atol=TOL, rtol=0)


def test_a_wrong_partner_is_detected():
    """Guard against a vacuous comparison: per-robot with a wrong partner must differ."""
    net = make_sensitive(DHCNetwork(ModelConfig.preset("dhc", "small")), 0).eval()
    rng = np.random.default_rng(0)
    positions = random_positions(rng, 6, 4)
    obs = synthetic_obs(rng, positions)
    with torch.no_grad():
        out = net.step(torch.from_numpy(obs)[None], torch.from_numpy(positions)[None])
        h = [net.encode(obs[i]) for i in range(6)]
        partners = out.partners[0, 0].tolist()
        wrong = [j for j in range(1, 6) if j not in partners][0]
        right = net.comm_round(0, h[0], [h[j] for j in partners if j >= 0])
        bad = net.comm_round(0, h[0], [h[wrong]])
    assert not torch.allclose(right, bad, atol=TOL)
