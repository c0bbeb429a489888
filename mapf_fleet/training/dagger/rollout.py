"""Rollouts: one episode of the policy under the arbiter, labelled by the expert at the states it
visits (with DAgger's mixing), recorded as a shard's arrays; plain PIBT for the baseline; and
`DaggerWorker`, the worker pool's unit that plays them (a Ray actor, or in-process)."""

from __future__ import annotations

import os
import time

import numpy as np
import torch

from ..replay import pack_cost_to_go, pack_obs
from .config import DaggerConfig
from .labeller import LabelState, Labeller, make_labeller


def window_starts(length: int, seq_len: int, burn_in: int) -> np.ndarray:
    """Step index where window j's unroll begins (its stored hidden state): max(0, j L - B)."""
    return np.maximum(0, np.arange(0, length, seq_len) - burn_in).astype(np.int64)


def play_episode(model, instance, max_steps: int, conflict_rule: str, ranking: str,
                 device, labeller: Labeller | None = None, beta: float = 0.0,
                 label_interval: int = 1, rng: np.random.Generator | None = None,
                 seq_len: int = 16, burn_in: int = 8, record: bool = True,
                 backoff_max: int = 1, shadow: Labeller | None = None,
                 anchor_patience: int | None = None, guidance: str = "none") -> dict:
    """One episode of `model` under `conflict_rule` (its Q-values ranked by `ranking`); with a
    labeller, the visited states are labelled (and the expert's ranking executed with
    probability `beta` at labelled steps). Returns the outcome and, with `record`, the arrays of
    a shard (`data.py`).

    `model` None: the policy is plain PIBT (the distance ranking, no network; nothing to
    record), so with `beta` 1 the labeller itself is the policy wherever it labels (the expert
    ceiling; `labels_executed` counts the labels the rule let through unchanged). `shadow`: a
    second labeller labelling the same states (another seed); the agents both label count in
    `agree_pairs`, those labelled alike in `agree`."""
    from mapf_fleet.coordination.factory import make_shield
    from mapf_fleet.coordination.ranking import rank_actions, tie_breakers
    from mapf_fleet.grid.env import EnvConfig, MAPFEnv
    from mapf_fleet.grid.heuristic import bfs_distances_many
    from mapf_fleet.models.policy import LearnedPolicy

    rng = np.random.default_rng(0) if rng is None else rng
    if model is None and record:
        raise ValueError("play_episode: model None (plain PIBT) records nothing: record=False")
    observation = "paper" if model is None else model.config.observation
    cost_to_go = observation == "cost_to_go"
    env = MAPFEnv(instance, EnvConfig(max_steps=max_steps, observation=observation,
                                      guidance=guidance))
    obs = env.reset()
    n = instance.num_agents
    shield = make_shield(conflict_rule, instance.grid, instance.goals,
                         anchor_patience=anchor_patience, guidance=env.guidance)
    policy = None if model is None else LearnedPolicy(model, device)
    if policy is not None:
        policy.reset(1, n)
    distances = bfs_distances_many(instance.grid, instance.goals) if labeller else None
    ties_agents = np.arange(n)
    rec_obs, rec_ctg, rec_pos, rec_last, rec_labels, hiddens = [], [], [], [], [], []
    stats = {"labelled_states": 0, "labels": 0, "unsolved": 0, "too_long": 0, "skipped": 0,
             "expert_steps": 0, "label_seconds": 0.0, "label_cpu_seconds": 0.0, "disagree": 0,
             "disagree_off_goal": 0, "off_goal_labels": 0, "label_calls": 0, "agree": 0,
             "agree_pairs": 0, "labels_executed": 0}
    done, info = (env.on_goal().all(), {"success": bool(env.on_goal().all()), "steps": 0})
    next_label, wait = 0, label_interval
    while not done:
        t = env.steps
        if record:
            rec_obs.append(pack_obs(obs))
            if cost_to_go:
                rec_ctg.append(pack_cost_to_go(obs))
            rec_pos.append(env.positions.astype(np.int16))
            rec_last.append(env.last_actions.astype(np.int8))
            hiddens.append(policy.hidden[0].detach().to("cpu", torch.float16).numpy())
        ties = tie_breakers(ties_agents, t)
        if policy is None:
            rankings = rank_actions(obs, mode="distance", ties=ties)
        else:
            policy.act(obs[None].astype(np.float32), env.positions[None])
            rankings = rank_actions(obs, policy.q_values[0], ranking, ties=ties)
        label = np.full(n, -1, np.int8)
        if labeller is not None and t >= next_label:
            state = LabelState(instance.grid, env.positions, instance.goals, distances, t,
                               max_steps, shield.snapshot() if hasattr(shield, "snapshot")
                               else None)
            began, began_cpu = time.perf_counter(), time.process_time()
            expert, status = labeller.label(state)
            stats["label_seconds"] += time.perf_counter() - began
            stats["label_cpu_seconds"] += time.process_time() - began_cpu
            stats["label_calls"] += 1
            if shadow is not None:
                other = shadow.label(state).actions
                both = (expert >= 0) & (other >= 0)
                stats["agree_pairs"] += int(both.sum())
                stats["agree"] += int((both & (expert == other)).sum())
            if status != "ok":
                stats[status] += 1
            if status == "skipped" or 2 * int((expert >= 0).sum()) >= n:
                # most agents labelled (a pocket may not be), or none by design
                wait = label_interval
            else:  # back off (config: label_backoff_max)
                wait = min(max(wait, label_interval) * 2, max(backoff_max, label_interval))
            next_label = t + wait
            have = expert >= 0
            if have.any():
                label[have] = expert[have]
                stats["labelled_states"] += 1
                stats["labels"] += int(have.sum())
                off_goal = ~env.on_goal() & have
                differ = (rankings[:, 0] != expert) & have
                stats["disagree"] += int(differ.sum())
                stats["disagree_off_goal"] += int((differ & off_goal).sum())
                stats["off_goal_labels"] += int(off_goal.sum())
                if beta > 0 and rng.random() < beta:  # DAgger's mixing: the expert drives
                    # the expert's move first, then the distance order; unlabelled agents
                    # keep the policy's ranking
                    onehot = (np.arange(5) == expert[:, None]).astype(np.float64)
                    ranked = rank_actions(obs, onehot, "q_then_distance", ties=ties)
                    rankings = np.where(have[:, None], ranked, rankings)
                    stats["expert_steps"] += 1
        if record:
            rec_labels.append(label)
        executed = shield.step(env.positions, rankings).actions
        labelled = label >= 0
        stats["labels_executed"] += int((labelled & (executed == label)).sum())
        if policy is not None:
            policy.set_last_actions(executed[None])
        obs, _, done, info = env.step(executed)
    out = {"success": bool(info["success"]), "steps": int(info["steps"]),
           "num_agents": n, **stats}
    if record:
        length = len(rec_obs)
        starts = window_starts(length, seq_len, burn_in) if length else np.zeros(0, np.int64)
        hidden = (np.stack([hiddens[s] for s in starts]) if length
                  else np.zeros((0, n, model.config.hidden_dim), np.float16))
        out["arrays"] = {
            "obs_bits": np.stack(rec_obs) if length else np.zeros((0, n, 61), np.uint8),
            "positions": np.stack(rec_pos) if length else np.zeros((0, n, 2), np.int16),
            "last_actions": np.stack(rec_last) if length else np.zeros((0, n), np.int8),
            "labels": np.stack(rec_labels) if length else np.zeros((0, n), np.int8),
            "hidden_starts": starts, "hidden": hidden,
        }
        if cost_to_go:
            fov = obs.shape[-1]
            out["arrays"]["ctg"] = np.stack(rec_ctg) if length else np.zeros((0, n, fov, fov),
                                                                               np.int8)
    return out


def make_instance(task: dict, seed_words: list[int]):
    from mapf_fleet.grid.maps import generate_kind_instance

    return generate_kind_instance(task["kind"], task["size"], task["agents"],
                                  np.random.default_rng(seed_words))


def kind_code(kind: str) -> int:
    from mapf_fleet.grid.maps import GENERATED_KINDS

    return GENERATED_KINDS.index(kind)


class DaggerWorker:
    """Plays episodes (a Ray actor, or in-process): rollouts with labels, and held-out checks."""

    def __init__(self, cfg: DaggerConfig, model_config: dict):
        from mapf_fleet.models.checkpoint import build_model
        from mapf_fleet.models.config import ModelConfig

        torch.set_num_threads(cfg.threads)
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        self.cfg = cfg
        self.model = build_model(ModelConfig.from_dict(model_config)).eval()
        # inference on the CPU: batch 1, one agent set at a time, the GPU would not pay
        self.device = torch.device("cpu")
        self.labeller = make_labeller(cfg)
        self.version = None

    def set_weights(self, state_dict: dict, version) -> None:
        self.model.load_state_dict(state_dict)
        self.version = version

    def collect(self, job: dict) -> dict:
        cfg = self.cfg
        instance = make_instance(job["task"], job["seed_words"])
        out = play_episode(self.model, instance, job["task"]["max_steps"], cfg.conflict_rule,
                           cfg.ranking, self.device, self.labeller, job["beta"],
                           cfg.label_interval, np.random.default_rng(job["seed_words"] + [1]),
                           cfg.seq_len, cfg.burn_in, record=True,
                           backoff_max=cfg.label_backoff_max,
                           anchor_patience=cfg.anchor_patience, guidance=cfg.guidance)
        return {**out, "job": job, "pid": os.getpid(),
                "process_cpu_seconds": time.process_time()}

    def heldout(self, job: dict) -> dict:
        """One held-out episode; `job["heuristic"]`: plain PIBT (distance ranking, no network)."""
        cfg = self.cfg
        instance = make_instance(job["task"], job["seed_words"])
        if job.get("heuristic"):
            out = play_plain_pibt(instance, job["task"]["max_steps"], cfg.conflict_rule,
                                  cfg.anchor_patience, cfg.guidance)
        else:
            out = play_episode(self.model, instance, job["task"]["max_steps"], cfg.conflict_rule,
                               cfg.ranking, self.device, record=False,
                               anchor_patience=cfg.anchor_patience, guidance=cfg.guidance)
        return {**out, "job": job, "pid": os.getpid(),
                "process_cpu_seconds": time.process_time()}


def play_plain_pibt(instance, max_steps: int, conflict_rule: str,
                    anchor_patience: int | None = None, guidance: str = "none") -> dict:
    """The baseline: the shield over distance rankings (the heuristic checkpoint's rows)."""
    out = play_episode(None, instance, max_steps, conflict_rule, "distance", None, record=False,
                       anchor_patience=anchor_patience, guidance=guidance)
    return {"success": out["success"], "steps": out["steps"], "num_agents": out["num_agents"]}


def play_lifelong(instance, steps: int, conflict_rule: str, goal_seed: int,
                  labeller: Labeller | None = None, anchor_patience: int | None = None) -> dict:
    """A lifelong run (`fleet.run.FleetRun` with the lifelong task source: a new goal on arrival,
    robot i's goals from (goal_seed, i)) of `steps` ticks under `conflict_rule`, ranked by plain
    PIBT's distance ranking, or, with a labeller, its label first where it labels (the
    labeller as the policy; its other moves in the distance order). Returns the goals reached
    per tick (`throughput`)."""
    from mapf_fleet.coordination.ranking import rank_actions, tie_breakers
    from mapf_fleet.fleet.record import Decisions
    from mapf_fleet.fleet.run import FleetRun
    from mapf_fleet.fleet.tasks import LifelongTasks
    from mapf_fleet.grid.heuristic import bfs_distances_many
    from mapf_fleet.grid.goal_observer import GoalObserver

    run = FleetRun(instance.grid, instance.starts, LifelongTasks(grid=instance.grid,
                                                                 seed=int(goal_seed)),
                   instance.goals, rule=conflict_rule, max_steps=steps)
    if anchor_patience is not None and run.arbiter.shield is not None:
        run.arbiter.shield.anchor_patience = int(anchor_patience)
    agents = np.arange(run.num_robots)
    observer = GoalObserver(run.grid)  # searches a goal once, however often it comes back
    label_seconds, label_cpu, calls = 0.0, 0.0, 0
    while not run.finished():
        goals = np.asarray(run.goals, np.int64)
        obs = observer.observe(run.positions, goals)
        ties = tie_breakers(agents, run.tick)
        rankings = rank_actions(obs, mode="distance", ties=ties)
        if labeller is not None:
            distances = bfs_distances_many(run.grid, goals)  # the map's recent searches
            began, began_cpu = time.perf_counter(), time.process_time()
            shield = run.arbiter.shield
            expert = labeller.label(LabelState(run.grid, np.asarray(run.positions), goals,
                                               distances, run.tick, steps,
                                               shield.snapshot()
                                               if hasattr(shield, "snapshot") else None)).actions
            label_seconds += time.perf_counter() - began
            label_cpu += time.process_time() - began_cpu
            calls += 1
            have = expert >= 0
            onehot = (np.arange(5) == expert[:, None]).astype(np.float64)
            ranked = rank_actions(obs, onehot, "q_then_distance", ties=ties)
            rankings = np.where(have[:, None], ranked, rankings)
        run.step(Decisions.complete(run.tick, rankings))
    return {"throughput": run.goals_reached / steps, "goals_reached": int(run.goals_reached),
            "steps": steps, "num_agents": run.num_robots, "label_seconds": label_seconds,
            "label_cpu_seconds": label_cpu, "label_calls": calls}
