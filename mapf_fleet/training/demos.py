"""Demonstration warm start, DQfD-style (Hester et al. 2018), off by default.

Before stage 1 the learner trains for `demo_pretrain_updates` updates on demonstration episodes
only, with the n-step TD loss of normal training plus `demo_weight` x the large-margin loss

    J_E = mean over (step, agent) of  max_a [Q(s, a) + m * (a != a_E)] - Q(s, a_E)

which pushes the demonstrator's action a_E above every other action by the margin m
(`demo_margin`). With `demo_loss: cross_entropy` the warm start is behaviour cloning instead:
`demo_weight` x the cross-entropy of a_E under softmax(Q), no TD term (which of the two serves the
shield's rankings better: docs/results.md, "Training at the evaluation's density").
Demonstrators (`demo_source`):
  - "heuristic": the non-learned reference `mapf_fleet.grid.policies.heuristic_policy`;
  - "planner":   LaCAM (`mapf_fleet.coordination.planners.ClassicalPlanner`, pymapf), whose joint
    plan is replayed through `MAPFEnv` (agents of unsolved regions stay; plans longer than the
    step limit are cut there).
Episodes are drawn over the stage-1 settings (k agents on 10 + 5 (k - 1) maps, up to
`demo_max_agents`) with the training rewards (alpha 0), and stored with the hidden states the
current network produces along them, exactly like actor episodes, so they go through the same
`episode_to_sequences` and replay code.
"""

from __future__ import annotations

import numpy as np
import torch

from .config import TrainConfig
from .episodes import EpisodeRecord, episode_to_sequences
from .modelio import model_step
from .replay import PrioritizedSequenceReplay, pack_obs

DEMO_SOURCES = ("none", "heuristic", "planner")


def margin_loss(q: torch.Tensor, demo_actions: torch.Tensor, mask: torch.Tensor,
                margin: float) -> torch.Tensor:
    """DQfD supervised loss. q (..., A), demo_actions (...) int, mask (...) float -> scalar:
    the masked mean of max_a [q(a) + margin * (a != a_E)] - q(a_E) (0 when a_E leads by >= margin)."""
    penalty = torch.full_like(q, float(margin))
    penalty.scatter_(-1, demo_actions[..., None], 0.0)
    q_demo = q.gather(-1, demo_actions[..., None]).squeeze(-1)
    per_item = (q + penalty).max(-1).values - q_demo
    return (per_item * mask).sum() / mask.sum().clamp(min=1.0)


def cross_entropy_loss(q: torch.Tensor, demo_actions: torch.Tensor,
                       mask: torch.Tensor) -> torch.Tensor:
    """Behaviour cloning. q (..., A) read as logits, demo_actions (...) int, mask (...) float ->
    scalar: the masked mean of -log softmax(q)[a_E]."""
    log_p = torch.log_softmax(q, -1).gather(-1, demo_actions[..., None]).squeeze(-1)
    return -(log_p * mask).sum() / mask.sum().clamp(min=1.0)


def stage1_settings(cfg: TrainConfig) -> list[tuple[int, int]]:
    """(agents, map size) of the demonstrations: `demo_settings` when given, else those of
    stage 1 up to `demo_max_agents` (0 = all of stage 1)."""
    if cfg.demo_settings:
        return [(int(a), int(s)) for a, s in cfg.demo_settings]
    settings, agents, size = [], cfg.start_agents, cfg.start_map_size
    cap = cfg.demo_max_agents or cfg.final_agents
    while agents <= min(cfg.final_agents, cap):
        settings.append((agents, min(size, cfg.final_map_size)))
        agents, size = agents + 1, size + cfg.map_size_step
    return settings


def _planner_actions(instance, limit: int) -> np.ndarray | None:
    from mapf_fleet.coordination.planners import ClassicalPlanner, positions_to_actions

    plan = ClassicalPlanner("lacam", time_limit=2.0).plan(instance.grid, instance.starts,
                                                          instance.goals)
    if len(plan.positions) < 2:
        return None
    return positions_to_actions(plan.positions)[:limit]


def demo_episode(cfg: TrainConfig, model, source: str, num_agents: int, map_size: int,
                 rng: np.random.Generator) -> tuple[EpisodeRecord, bool]:
    """Play one demonstration episode; returns (record, success). The record's actions are the
    demonstrator's, its hidden states those `model` computes along the visited states."""
    from mapf_fleet.grid.env import EnvConfig, MAPFEnv
    from mapf_fleet.grid.instance import generate_instance, sample_training_density
    from mapf_fleet.grid.policies import heuristic_policy

    if source not in ("heuristic", "planner"):
        raise ValueError(f"demo_source must be 'heuristic' or 'planner', got {source!r}")
    density = (sample_training_density(rng) if cfg.obstacle_density == "triangular"
               else float(cfg.obstacle_density))
    instance = generate_instance(map_size, num_agents, density, rng)
    limit = cfg.episode_step_limit(map_size)
    env = MAPFEnv(instance, EnvConfig(max_steps=limit, finish_reward=cfg.finish_reward))
    obs = env.observe()
    plan = _planner_actions(instance, limit) if source == "planner" else None
    hidden = torch.zeros(1, num_agents, model.config.hidden_dim)
    rec_obs, rec_pos, rec_hidden = [pack_obs(obs)], [env.positions.astype(np.int16)], [hidden[0]]
    actions, rewards = [], []
    done, info = False, {"success": False}
    with torch.no_grad():
        while not done:
            out = model_step(model, cfg.algo, torch.from_numpy(obs[None]),
                             torch.from_numpy(env.positions[None].astype(np.int64)), hidden,
                             torch.from_numpy(env.last_actions[None].astype(np.int64)))
            hidden = out.hidden
            if plan is not None:
                step = env.steps
                action = plan[step] if step < len(plan) else np.zeros(num_agents, np.int64)
            else:
                action = heuristic_policy(obs)
            obs, reward, done, info = env.step(action)
            actions.append(action.astype(np.uint8))
            rewards.append(reward)
            rec_obs.append(pack_obs(obs))
            rec_pos.append(env.positions.astype(np.int16))
            rec_hidden.append(hidden[0])
    record = EpisodeRecord(obs=np.stack(rec_obs), positions=np.stack(rec_pos),
                           actions=np.stack(actions), rewards=np.stack(rewards),
                           hidden=torch.stack(rec_hidden).numpy().astype(np.float16),
                           terminal=bool(info["success"]))
    return record, bool(info["success"])


def demo_replay(cfg: TrainConfig, model, num_episodes: int, seed: int):
    """Demonstration sequences in a prioritized replay of their own; returns (replay, stats)."""
    rng = np.random.default_rng(seed)
    settings = stage1_settings(cfg)
    sequences, successes, steps = [], 0, 0
    model.eval()
    for k in range(num_episodes):
        agents, size = settings[k % len(settings)]
        record, success = demo_episode(cfg, model, cfg.demo_source, agents, size, rng)
        successes += success
        steps += record.length
        sequences.extend(episode_to_sequences(record, cfg.seq_len, cfg.burn_in, cfg.n_step,
                                              cfg.gamma))
    replay = PrioritizedSequenceReplay(max(1, len(sequences)), cfg.window_len, cfg.seq_len,
                                       cfg.final_agents, model.config.hidden_dim,
                                       cfg.priority_alpha, cfg.priority_epsilon, seed)
    for seq in sequences:
        replay.add(seq)
    return replay, {"episodes": num_episodes, "success_rate": successes / max(1, num_episodes),
                    "steps": steps, "sequences": len(sequences), "settings": settings}


def demo_update(learner, replay, cfg: TrainConfig, writer=None) -> dict:
    """One learner update on a batch of demonstrations (TD + margin loss); logs under demo/."""
    batch = replay.sample(cfg.batch_size, cfg.priority_beta)
    priorities, stats = learner.update(batch, demo_weight=cfg.demo_weight,
                                       demo_margin=cfg.demo_margin, demo_loss=cfg.demo_loss)
    replay.update_priorities(batch.indices, priorities)
    if writer is not None and learner.updates % 10 == 0:
        for key in ("loss", "td_loss", "margin_loss", "cross_entropy", "demo_agreement",
                    "mean_q"):
            if key in stats:
                writer.add_scalar(f"demo/{key}", stats[key], learner.updates)
    return stats


def make_demo_replay(learner, cfg: TrainConfig, log=None):
    """Fresh demonstrations (deterministic in cfg.seed) in their own replay."""
    replay, info = demo_replay(cfg, learner.model, cfg.demo_episodes, cfg.seed + 7919)
    if log:
        log(f"demo warm start: {info['episodes']} {cfg.demo_source} episodes "
            f"(success {info['success_rate']:.2f}), {info['sequences']} sequences")
    return replay, info


def pretrain(learner, cfg: TrainConfig, writer=None, log=None, replay=None,
             on_update=None) -> dict:
    """Run the warm start on demonstrations (fresh ones unless `replay` is given); returns a
    summary (also logged). The replay stays usable for `demo_interleave`. `on_update(stats)`
    is called after every update (the trainer's progress bar)."""
    info: dict = {}
    if replay is None:
        replay, info = make_demo_replay(learner, cfg, log)
    stats: dict = {}
    for _ in range(cfg.demo_pretrain_updates):
        stats = demo_update(learner, replay, cfg, writer)
        if on_update is not None:
            on_update(stats)
    learner.sync_target()
    summary = {**info, "updates": cfg.demo_pretrain_updates,
               "final_agreement": stats.get("demo_agreement"),
               "final_margin_loss": stats.get("margin_loss"),
               "final_cross_entropy": stats.get("cross_entropy")}
    summary.pop("settings", None)
    return summary
