"""The fleet's exchange (`models.exchange.PolicyExchange`, what every policy process runs)
without ROS: several processes' exchanges linked in memory (`LinkedExchanges`) reproduce the
batched `model.step` (the same actions, Q-values and communication), on the grid world's
observations and on synthetic ones, each robot alone in its process; a message left out
(timeout) leaves the robot deciding on what it has; the mailbox drops stale ticks and keeps
early messages."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from mapf_fleet.grid.actions import ACTION_DELTAS
from mapf_fleet.grid.env import EnvConfig, MAPFEnv
from mapf_fleet.grid.instance import generate_instance
from mapf_fleet.models import DCCNetwork, DHCNetwork, ModelConfig
from mapf_fleet.models.checkpoint import with_observation
from mapf_fleet.models.exchange import LinkedExchanges
from mapf_fleet.models.mailbox import Mailbox
from mapf_fleet.models.synthetic import make_sensitive, random_positions, synthetic_obs

TOL = 1e-5


@pytest.fixture(autouse=True)
def _one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def _model(name: str, preset: str = "small", seed: int = 7, **overrides):
    """A small network with random weights; "dcc_sensitive": DCC whose weights make its causal
    sets non-empty (robots really request and reply); "X+cost_to_go": X for the "cost_to_go"
    observation, its new channel's weights made non-zero so the channel matters."""
    name, _, observation = name.partition("+")
    algo = name.split("_")[0]
    torch.manual_seed(seed)
    config = ModelConfig.preset(algo, preset, **overrides)
    model = DHCNetwork(config) if algo == "dhc" else DCCNetwork(config)
    if name.endswith("sensitive"):
        make_sensitive(model, seed=3)
    if observation:
        model = with_observation(model, observation)
        torch.manual_seed(5)
        with torch.no_grad():
            model.obs_encoder[0].weight[:, -1].normal_(0.0, 0.5)
    return model.eval()


def _batched(model, obs, positions, hidden, last_actions):
    with torch.no_grad():
        kwargs = {"last_action": torch.as_tensor(last_actions)[None]} \
            if model.config.algo == "dcc" else {}
        return model.step(torch.as_tensor(obs)[None], torch.as_tensor(positions)[None], hidden,
                          **kwargs)


def _assert_same(got, out, n, where, b=0):
    """The exchange's decisions equal episode b of the batched step: actions, Q-values, and who
    talked to whom (DCC: the decision-causal mask; DHC: the partners)."""
    np.testing.assert_array_equal(got.rankings[:, 0], out.actions[b, :n].numpy(),
                                  err_msg=where)
    np.testing.assert_allclose(got.q, out.q[b, :n].numpy(), atol=TOL, rtol=0, err_msg=where)
    comm = out.comm_mask[b, :n, :n].numpy()
    for i in range(n):
        assert sorted(got.requested[i]) == np.flatnonzero(comm[i]).tolist(), (where, i)
        assert not got.missing[i], (where, i)  # nothing left out


@pytest.mark.parametrize("algo", ["dhc", "dcc_sensitive", "dcc_sensitive+cost_to_go",
                                  "dhc+cost_to_go"])
def test_linked_exchanges_equal_the_batched_step(algo):
    """Three "processes" of uneven size on the grid world: the first choices (`q` ranking),
    the Q-values and who talked to whom equal the batched step's, tick after tick (with the
    observation the model reads)."""
    model = _model(algo)
    for seed in (1, 2):
        instance = generate_instance(12, 10, 0.25, seed)
        env = MAPFEnv(instance, EnvConfig(observation=model.config.observation))
        obs, hidden = env.reset(), None
        fleet = LinkedExchanges(model, [[0, 3, 7], [1, 2, 4, 5], [6, 8, 9]])
        talked = 0
        for tick in range(20):
            out = _batched(model, obs, env.positions, hidden, env.last_actions)
            got = fleet.tick(9, tick, env.positions, env.last_actions, instance.grid,
                             instance.goals)
            _assert_same(got, out, 10, f"seed {seed} tick {tick}")
            talked += sum(got.received)
            hidden = out.hidden
            obs, _, done, _ = env.step(out.actions[0].numpy())
            if done:
                break
        assert talked > 0  # the robots really exchanged messages
    if algo.startswith("dcc"):
        assert fleet.calls > 0  # requests / replies crossed "processes", batched per pair


def _move(positions: np.ndarray, actions: np.ndarray, side: int) -> np.ndarray:
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


def _pad(arrays, width, fill=0):
    out = np.full((len(arrays), width) + arrays[0].shape[1:], fill, dtype=arrays[0].dtype)
    for b, a in enumerate(arrays):
        out[b, : len(a)] = a
    return out


def run_one_robot_per_process(algo: str, preset: str, counts, side: int, seed: int,
                              steps: int = 4, **overrides) -> int:
    """Each robot alone in its process, so it sees only its own observation and the messages it
    receives, equals the batched step over consecutive steps (synthetic observations, dense or
    sparse crowds; several episodes of `counts` robots batched with padding, the padded slots
    at (0, 0) inside the map, so that a broken agent_mask shows as an extra neighbour). Returns
    how many messages were used (to show the test is not vacuous)."""
    rng = np.random.default_rng(seed)
    model = make_sensitive(_model(algo, preset, seed, **overrides), seed).eval()
    width = max(counts)
    fleets = [LinkedExchanges(model, [[i] for i in range(n)]) for n in counts]
    positions = [random_positions(rng, n, side) for n in counts]
    hidden = torch.zeros(len(counts), width, model.config.hidden_dim)
    last = [np.full(n, -1) for n in counts]
    agent_mask = torch.from_numpy(_pad([np.ones(n, bool) for n in counts], width, False))
    messages = 0
    for step in range(steps):
        obs = [synthetic_obs(rng, p, model.config.obs_radius) for p in positions]
        with torch.no_grad():
            kwargs = {"last_action": torch.from_numpy(_pad(last, width, -1))} \
                if algo == "dcc" else {}
            out = model.step(torch.from_numpy(_pad(obs, width)),
                             torch.from_numpy(_pad(positions, width)), hidden,
                             agent_mask=agent_mask, **kwargs)
        for b, n in enumerate(counts):
            got = fleets[b].tick(1, step, positions[b], last[b], obs=obs[b])
            _assert_same(got, out, n, f"{algo}/{preset} {counts} on {side} seed {seed} "
                                      f"step {step} episode {b}", b)
            messages += sum(got.received)
            last[b] = out.actions[b, :n].numpy()
            positions[b] = _move(positions[b], last[b], side)
        hidden = out.hidden
    return messages


CROWDS = {"pair": ([2], 4), "dense16": ([16], 7), "sparse16": ([16], 30),
          "padded_mix": ([5, 12, 3], 9)}


@pytest.mark.parametrize("seed", range(2))
@pytest.mark.parametrize("crowd", sorted(CROWDS))
@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_one_robot_per_process_equals_the_batched_step(algo, crowd, seed):
    messages = run_one_robot_per_process(algo, "small", *CROWDS[crowd], seed)
    if crowd.startswith("dense"):
        assert messages > 0, "no communication happened: the test would prove nothing"


@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_paper_preset_one_robot_per_process_equals_the_batched_step(algo):
    assert run_one_robot_per_process(algo, "paper", [16], 7, seed=11) > 0


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_dense64_one_robot_per_process_equals_the_batched_step(algo):
    assert run_one_robot_per_process(algo, "paper", [64], 14, seed=0, steps=2) > 0


def test_dcc_reference_variant_without_self_attention_is_also_equivalent():
    """attend_self=False (the DCC reference's attention over senders only) keeps them equal."""
    assert run_one_robot_per_process("dcc", "small", [24], 8, seed=3, attend_self=False) > 0


def test_a_vector_left_out_is_reported_and_changes_the_q_values():
    """Guard against a vacuous comparison: a robot that does not hear its partners' vectors
    reports them missing and decides on other Q-values than the batched step."""
    model = make_sensitive(_model("dhc"), 0).eval()
    rng = np.random.default_rng(0)
    positions = random_positions(rng, 6, 4)
    obs = synthetic_obs(rng, positions)
    out = _batched(model, obs, positions, None, np.full(6, -1))
    partners = [j for j in out.partners[0, 0].tolist() if j >= 0]
    assert partners
    fleet = LinkedExchanges(model, [[i] for i in range(6)], comm_timeout=0.2)
    fleet.exchanges[0].receive_hidden = lambda *message: None  # robot 0 hears nobody
    got = fleet.tick(1, 0, positions, obs=obs)
    assert got.missing[0] == set(partners)
    assert not np.allclose(got.q[0], out.q[0, 0].numpy(), atol=TOL)


def test_a_reply_left_out_still_decides():
    """A reply that never arrives is left out after comm_timeout: the requester decides on what
    it has and reports the peer missing."""
    model = _model("dcc_sensitive")
    instance = generate_instance(8, 10, 0.1, 5)
    dropped = []

    def drop(kind, sender, receiver):
        if kind == "reply":
            dropped.append((sender, receiver))
            return True
        return False

    fleet = LinkedExchanges(model, [list(range(5)), list(range(5, 10))], comm_timeout=0.2,
                            drop=drop)
    env = MAPFEnv(instance)
    env.reset()
    for tick in range(30):
        got = fleet.tick(3, tick, env.positions, env.last_actions, instance.grid,
                         instance.goals)
        actions = got.rankings[:, 0]
        assert ((0 <= actions) & (actions < 5)).all()
        if dropped:
            senders = {s for s, _ in dropped}
            receivers = {r for _, r in dropped}
            assert any(got.missing[r] & senders for r in receivers)  # reported as left out
            break
        _, _, done, _ = env.step(actions)
        if done:
            break
    assert dropped  # on this crowded instance a reply crossed processes and was dropped


def test_mailbox_ignores_stale_ticks_and_times_out():
    box = Mailbox()
    box.set_tick(episode=1, tick=5)
    assert not box.put(1, "dhc0", 4, sender=2, payload="old")   # stale tick
    assert not box.put(2, "dhc0", 5, sender=2, payload="other")  # another episode
    assert box.put(1, "dhc0", 5, sender=3, payload="ok")
    assert box.put(1, "dhc0", 6, sender=3, payload="early")      # a faster peer: kept
    assert box.put_many(1, "dhc1", 4, [(5, "old")]) == 0          # a stale batch
    assert box.put_many(1, "dhc1", 5, [(5, "a"), (6, "b")]) == 2
    assert box.stale_dropped == 3
    start = time.monotonic()
    got = box.wait_for("dhc0", 5, [2, 3], deadline=time.monotonic() + 0.2)
    assert got == {3: "ok"}                                       # 2 left out after timeout
    assert time.monotonic() - start >= 0.19
    assert box.wait_for("dhc1", 5, [5, 6], deadline=time.monotonic()) == {5: "a", 6: "b"}
    box.set_tick(1, 6)
    assert box.wait_for("dhc0", 6, [3], deadline=time.monotonic()) == {3: "early"}


def test_mailbox_keeps_messages_that_arrive_before_the_first_state():
    """A faster peer's round-0 vector can arrive before this node has seen tick 0: entering the
    episode must not discard it (a lost message here made the fleet leave a partner out)."""
    box = Mailbox()
    assert box.put(7, "dhc0", 0, sender=4, payload="early")
    assert box.put(6, "dhc0", 0, sender=5, payload="other run")
    box.set_tick(episode=7, tick=0)
    assert box.wait_for("dhc0", 0, [4, 5], deadline=time.monotonic()) == {4: "early"}
