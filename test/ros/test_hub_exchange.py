"""The fleet's one per-robot exchange (`hub.HubExchange`, what every policy process runs) without
ROS: several processes' exchanges linked in memory reproduce the batched network step (actions
and communication); a message left out (timeout) leaves the robot deciding on what it has; the
mailbox drops stale ticks and keeps early messages."""

from __future__ import annotations

import threading
import time
from collections import defaultdict

import numpy as np
import pytest
import torch

from mapf_fleet.grid.env import EnvConfig, MAPFEnv
from mapf_fleet.grid.instance import generate_instance
from mapf_fleet.models.checkpoint import load_checkpoint, with_observation
from mapf_fleet.ros.hub import HubExchange
from mapf_fleet.ros.mailbox import Mailbox


class MemoryFleet:
    """Exchanges of robot groups (one per "process") linked by direct calls: the ROS link's
    deliveries without DDS. `drop(kind, sender, receiver)` loses a DCC request / reply."""

    def __init__(self, model, groups, comm_timeout=5.0, drop=None):
        self.drop = drop or (lambda kind, sender, receiver: False)
        self.exchanges = [HubExchange(model, group, comm_timeout, "q", _Link(self, k))
                          for k, group in enumerate(groups)]
        self.owner = {int(r): ex for ex in self.exchanges for r in ex.ids}
        self.calls = 0

    def tick(self, episode, tick, grid, positions, goals, last_actions):
        """Every exchange decides in its own thread (they wait for each other's messages);
        per robot id: (ranked actions, requested, received, missing)."""
        results, errors = {}, []

        def run(ex):
            try:
                ex.enter(episode, tick)
                results[id(ex)] = ex.decide(grid, positions, goals, last_actions)
            except Exception as exc:  # reported below
                errors.append(exc)

        threads = [threading.Thread(target=run, args=(ex,)) for ex in self.exchanges]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(60)
        assert not errors, errors
        out = {}
        for ex in self.exchanges:
            preferences, requested, received, missing = results[id(ex)]
            for m, robot in enumerate(ex.ids.tolist()):
                out[robot] = (preferences[m], requested[m], received[m], missing[m])
        return out


class _Link:
    def __init__(self, fleet: MemoryFleet, index: int):
        self.fleet, self.index = fleet, index

    def _others(self):
        return [ex for k, ex in enumerate(self.fleet.exchanges) if k != self.index]

    def publish_hidden(self, episode, tick, round_index, ids, vectors):
        for ex in self._others():
            ex.receive_hidden(episode, tick, round_index, ids.tolist(), vectors.copy())

    def publish_announce(self, episode, tick, ids, targets):
        for ex in self._others():
            ex.receive_announce(episode, tick, ids.tolist(), [list(t) for t in targets])

    def send(self, kind, episode, tick, entries):
        by_owner = defaultdict(list)
        for sender, receiver, vector in entries:
            if not self.fleet.drop(kind, sender, receiver):
                by_owner[id(self.fleet.owner[receiver])].append((sender, receiver, vector))
        for batch in by_owner.values():
            owner = self.fleet.owner[batch[0][1]]
            owner.receive(kind, episode, tick, [e[0] for e in batch], [e[1] for e in batch],
                          np.stack([e[2] for e in batch]))
            self.fleet.calls += 1
        return sum(len(b) for b in by_owner.values()), len(by_owner)

    def warn(self, text):
        pass


def _batched(model, env, obs, hidden):
    with torch.no_grad():
        if model.config.algo == "dhc":
            out = model.step(obs[None], env.positions[None], hidden)
        else:
            out = model.step(obs[None], env.positions[None], hidden, env.last_actions[None])
    return out.actions[0].numpy(), out.comm_mask[0].numpy(), out.hidden


def _model(checkpoints, name: str):
    """A checkpoint's network; "X+cost_to_go": X's warm-started for the "cost_to_go"
    observation, its new channel's weights made non-zero so the channel matters."""
    algo, _, observation = name.partition("+")
    model, _ = load_checkpoint(checkpoints[algo])
    if observation:
        model = with_observation(model, observation)
        torch.manual_seed(5)
        with torch.no_grad():
            model.obs_encoder[0].weight[:, -1].normal_(0.0, 0.5)
    return model


@pytest.mark.parametrize("algo", ["dhc", "dcc_sensitive", "dcc_sensitive+cost_to_go"])
def test_linked_exchanges_equal_the_batched_step(checkpoints, algo):
    """Three "processes" of uneven size: the first choices (`q` ranking) and who talked to
    whom equal the batched step's actions and comm_mask, tick after tick (with the
    observation the model reads)."""
    torch.set_num_threads(1)
    model = _model(checkpoints, algo)
    for seed in (1, 2):
        instance = generate_instance(12, 10, 0.25, seed)
        env = MAPFEnv(instance, EnvConfig(observation=model.config.observation))
        obs, hidden = env.reset(), None
        fleet = MemoryFleet(model, [[0, 3, 7], [1, 2, 4, 5], [6, 8, 9]])
        talked = 0
        for tick in range(20):
            actions, comm, hidden = _batched(model, env, obs, hidden)
            got = fleet.tick(9, tick, instance.grid, env.positions, instance.goals,
                             env.last_actions)
            np.testing.assert_array_equal([got[i][0][0] for i in range(10)], actions,
                                          err_msg=f"seed {seed} tick {tick}")
            for i in range(10):
                assert sorted(got[i][1]) == np.flatnonzero(comm[i]).tolist(), (seed, tick, i)
                assert not got[i][3], (seed, tick, i)  # nothing left out
                talked += got[i][2]
            obs, _, done, _ = env.step(actions)
            if done:
                break
        assert talked > 0  # the robots really exchanged messages
    if algo == "dcc_sensitive":
        assert fleet.calls > 0  # requests / replies crossed "processes", batched per pair


def test_a_reply_left_out_still_decides(checkpoints):
    """A reply that never arrives is left out after comm_timeout: the requester decides on what
    it has and reports the peer missing."""
    model, _ = load_checkpoint(checkpoints["dcc_sensitive"])
    instance = generate_instance(8, 10, 0.1, 5)
    dropped = []

    def drop(kind, sender, receiver):
        if kind == "reply":
            dropped.append((sender, receiver))
            return True
        return False

    fleet = MemoryFleet(model, [list(range(5)), list(range(5, 10))], comm_timeout=0.2,
                        drop=drop)
    env = MAPFEnv(instance)
    env.reset()
    for tick in range(30):
        got = fleet.tick(3, tick, instance.grid, env.positions, instance.goals, env.last_actions)
        actions = np.array([got[i][0][0] for i in range(10)])
        assert ((0 <= actions) & (actions < 5)).all()
        if dropped:
            senders = {s for s, _ in dropped}
            receivers = {r for _, r in dropped}
            assert any(got[r][3] & senders for r in receivers)  # reported as left out
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
