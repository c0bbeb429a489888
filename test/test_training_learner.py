"""The learner against an independent full-episode unroll: obs/action/reward/next-obs alignment,
stored hidden state and burn-in, padding of short sequences, terminal cut, timeouts."""

import numpy as np
import pytest
import torch

from mapf_fleet.training.actor import EpisodeWorker, Task
from mapf_fleet.training.config import TrainConfig
from mapf_fleet.training.episodes import EpisodeRecord, episode_to_sequences
from mapf_fleet.training.learner import Learner
from mapf_fleet.training.modelio import model_step
from mapf_fleet.training.replay import PrioritizedSequenceReplay, unpack_obs


def _cfg(algo="dhc", **kw):
    base = dict(algo=algo, model_preset="small", num_actors=1, envs_per_actor=3,
                max_episode_steps=11, seq_len=4, burn_in=2, n_step=2, gamma=0.9,
                final_agents=3, final_map_size=10, obstacle_density=0.1, seed=0)
    base.update(kw)
    return TrainConfig(**base)


def _full_unroll(net, algo, rec):
    """Q (T+1, N, 5) of one recorded episode, stepping from a zero hidden state."""
    obs = unpack_obs(rec.obs) if rec.obs.dtype == np.uint8 else rec.obs
    n = rec.actions.shape[1]
    h = torch.zeros(1, n, net.config.hidden_dim)
    last = np.concatenate([np.full((1, n), -1), rec.actions.astype(np.int64)])
    qs = []
    with torch.no_grad():
        for t in range(rec.length + 1):
            out = model_step(net, algo, torch.as_tensor(obs[t][None]),
                             torch.as_tensor(rec.positions[t][None].astype(np.int64)), h,
                             torch.as_tensor(last[t][None]))
            h = out.hidden
            qs.append(out.q[0].numpy())
    return np.stack(qs)


def _check_learner(learner, cfg, records, sequences, num_agents):
    """Every trained (step, agent) of `sequences` (cut from `records` in order) against
    n-step targets computed by hand from a full unroll of each episode."""
    replay = PrioritizedSequenceReplay(len(sequences), cfg.window_len, cfg.seq_len,
                                       cfg.final_agents, learner.model.config.hidden_dim)
    owners = [(r_index, t0) for r_index, rec in enumerate(records)
              for t0 in range(0, rec.length, cfg.seq_len)]
    assert len(owners) == len(sequences)
    for seq in sequences:
        replay.add(seq)
    batch = replay.sample(len(replay), beta=0.4)
    idx = np.arange(len(replay))  # every slot once, in order (sample() gave the layout)
    for name in ("positions", "last_actions", "actions", "returns", "boot_discount",
                 "boot_index", "step_mask", "agent_mask", "start_index", "hidden"):
        setattr(batch, name, getattr(replay, name)[idx].astype(getattr(batch, name).dtype))
    batch.obs = unpack_obs(replay.obs_bits[idx])
    with torch.no_grad():
        q_taken, target, mask = learner.q_and_targets(batch)
    q_full = [_full_unroll(learner.model, cfg.algo, rec) for rec in records]
    checked = 0
    for row, (r_index, t0) in enumerate(owners):
        rec, q = records[r_index], q_full[r_index]
        for k in range(cfg.seq_len):
            t = t0 + k
            if t >= rec.length:
                assert mask[row, k].sum() == 0  # padding of the episode's last sequence
                continue
            m = min(cfg.n_step, rec.length - t)
            ret = sum(cfg.gamma ** j * rec.rewards[t + j] for j in range(m))
            terminal_cut = rec.terminal and t + m == rec.length
            boot = 0.0 if terminal_cut else cfg.gamma ** m * q[t + m].max(-1)
            np.testing.assert_allclose(target[row, k].numpy(), ret + boot, atol=2e-3)
            expected_q = q[t][np.arange(num_agents), rec.actions[t]]
            # stored hidden states are float16: small rounding only
            np.testing.assert_allclose(q_taken[row, k].numpy(), expected_q, atol=2e-3)
            checked += 1
    assert checked == sum(r.length for r in records)


@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_learner_matches_unroll_on_actor_episodes_cut_by_the_time_limit(algo):
    torch.manual_seed(0)
    cfg = _cfg(algo)
    learner = Learner(cfg, device="cpu")
    worker = EpisodeWorker(cfg, actor_index=0, seed=2)
    worker.set_weights(learner.cpu_weights(), 0)  # actor, online and target share weights
    worker.keep_records = True
    worker.set_task(Task(num_agents=3, map_size=10, alpha=0.0))
    result = worker.run(30)
    assert worker.records and not any(r.terminal for r in worker.records)
    _check_learner(learner, cfg, worker.records, result["sequences"], 3)


def _heuristic_episode(net, algo, seed):
    """One agent following the BFS bits to its goal (terminal, +3 on the last step), with the
    hidden states the network produces along the way (what an actor would store)."""
    from mapf_fleet.grid.env import EnvConfig, MAPFEnv
    from mapf_fleet.grid.instance import generate_instance
    from mapf_fleet.grid.policies import heuristic_policy

    rng = np.random.default_rng(seed)
    while True:
        env = MAPFEnv(generate_instance(10, 1, 0.2, rng), EnvConfig(max_steps=64))
        obs = [env.observe()]
        positions, actions, rewards = [env.positions.copy()], [], []
        done = False
        while not done:
            a = heuristic_policy(obs[-1])
            o, r, done, info = env.step(a)
            obs.append(o), positions.append(env.positions.copy()), actions.append(a)
            rewards.append(r)
        if len(actions) >= 6:  # long enough to span two sequences
            break
    hidden = [np.zeros((1, net.config.hidden_dim), np.float32)]
    with torch.no_grad():
        for t in range(len(actions)):
            last = np.array([[-1 if t == 0 else actions[t - 1][0]]])
            out = model_step(net, algo, torch.as_tensor(obs[t][None]),
                             torch.as_tensor(positions[t][None]), torch.as_tensor(hidden[-1][None]),
                             torch.as_tensor(last))
            hidden.append(out.hidden[0].numpy())
    return EpisodeRecord(obs=np.stack(obs), positions=np.stack(positions),
                         actions=np.stack(actions), rewards=np.stack(rewards),
                         hidden=np.stack(hidden).astype(np.float16), terminal=bool(info["success"]))


@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_learner_cuts_bootstrap_at_success_and_keeps_the_finish_reward(algo):
    torch.manual_seed(1)
    cfg = _cfg(algo, seq_len=4, burn_in=1)
    learner = Learner(cfg, device="cpu")
    records = [_heuristic_episode(learner.model, algo, seed) for seed in (3, 4)]
    assert all(r.terminal and r.rewards[-1, 0] == pytest.approx(3.0) for r in records)
    sequences = [s for r in records
                 for s in episode_to_sequences(r, cfg.seq_len, cfg.burn_in, cfg.n_step, cfg.gamma)]
    _check_learner(learner, cfg, records, sequences, 1)
