"""The expert ceiling: a label scheme run as the policy itself, beside plain PIBT.

    mapf-fleet dagger --expert-ceiling --config config/training/dagger_committed.yaml [--count N]
        [--set labeller=lacam] [--json OUT]

A policy that imitated its labels perfectly would play as the labeller does at the states it
visits; so the labeller's closed loop under the configured conflict rule (`conflict_rule`) is the most
that imitating it can reach. For each one-shot suite of `ceiling` ({kind, size, agents: [..],
max_steps}; `ceiling_count` generated instances per agent count (`--count`), instance i from the seed
sequence (ceiling_seed, crc32(kind), size, agents, i), the evaluator's generated sets) it plays
every instance twice through the rollout of DAgger (`rollout.play_episode`, no network):
- plain PIBT: the rule over the distance ranking (`play_plain_pibt`);
- the labeller as the policy: every state labelled (`label_interval`, backing off as DAgger does
  after states it cannot label, `label_backoff_max`), the label executed first and the distance
  order after it (DAgger's mixing with beta = 1); agents without a label keep plain PIBT's
  ranking.
It reports success, average steps (the step limit for a failure), the success no method can
pass (the instances LaCAM does not prove unsolvable, `coordination.lacam.solvability`: generated
maps shut agents into pockets where they cannot pass each other), the labeller's CPU seconds
(all its calls) per labelled state and per agent label, the fraction of labels the rule executed
unchanged, the fraction of calls that left agents unlabelled, plans per episode, and its
self-agreement: on the first `ceiling_agreement_episodes` episodes a second labeller (planner
seed + the searches per re-plan, `committed_restarts`: no search seed shared with the first's)
labels the same states, and the agreement is the fraction of agents both label whose
labels match. For each lifelong suite (`ceiling_lifelong`) it reports goals
reached per tick over `max_steps` ticks on the first `ceiling_lifelong_count` instances
(`rollout.play_lifelong`, the fleet's lifelong source, goals seeded per episode).

Planning budgets are wall clock: on a loaded machine a labeller finds fewer plans; run it niced
on a quiet one and say where it ran."""

from __future__ import annotations

import statistics
import time
import zlib

import numpy as np

from mapf_fleet.coordination.lacam import solvability

from .config import DaggerConfig
from .labeller import make_labeller
from .rollout import make_instance, play_episode, play_lifelong, play_plain_pibt


def ceiling_instances(task: dict, agents: int, count: int, seed: int) -> list:
    """`count` instances of a suite: instance i from (seed, crc32(kind), size, agents, i)."""
    code = zlib.crc32(task["kind"].encode())
    return [make_instance({**task, "agents": agents}, [seed, code, task["size"], agents, i])
            for i in range(count)]


def _suite_name(task: dict) -> str:
    if task["kind"] == "dense":
        return f"dense {task['size'] - 4}-{task['size']}"
    return f"{task['kind']} {task['size']}x{task['size']}"


def _plans(labeller, out: dict) -> int:
    replans = getattr(labeller, "replans", None)
    return out["label_calls"] if replans is None else replans


def one_shot_row(cfg: DaggerConfig, task: dict, agents: int, count: int, log=None) -> dict:
    instances = ceiling_instances(task, agents, count, cfg.ceiling_seed)
    steps = task["max_steps"]
    plain = [play_plain_pibt(inst, steps, cfg.conflict_rule, cfg.anchor_patience)
             for inst in instances]
    unsolvable = [k for k, inst in enumerate(instances)
                  if solvability(inst.grid, inst.starts, inst.goals)[0] == "unsolvable"]
    expert, plans, agree, pairs = [], 0, 0, 0
    began = time.process_time()
    for k, inst in enumerate(instances):
        labeller = make_labeller(cfg)
        # the first labeller's searches use seeds seed .. seed + restarts - 1: none shared
        shadow = (make_labeller(cfg, seed=cfg.planner_seed + max(1, cfg.committed_restarts))
                  if k < cfg.ceiling_agreement_episodes else None)
        before = _plans(labeller, {"label_calls": 0})
        out = play_episode(None, inst, steps, cfg.conflict_rule, "distance", None, labeller, beta=1.0,
                           label_interval=cfg.label_interval,
                           rng=np.random.default_rng([cfg.ceiling_seed, k]), record=False,
                           backoff_max=cfg.label_backoff_max, shadow=shadow,
                           anchor_patience=cfg.anchor_patience)
        plans += _plans(labeller, out) - before
        agree, pairs = agree + out["agree"], pairs + out["agree_pairs"]
        expert.append(out)
    calls = sum(o["label_calls"] for o in expert)
    labelled = sum(o["labelled_states"] for o in expert)
    labels = sum(o["labels"] for o in expert)
    cpu = sum(o["label_cpu_seconds"] for o in expert)
    row = {
        "suite": _suite_name(task), "kind": task["kind"], "size": task["size"],
        "agents": agents, "instances": count, "max_steps": steps, "rule": cfg.conflict_rule,
        "labeller": cfg.labeller,
        "pibt_success": sum(p["success"] for p in plain) / count,
        "pibt_steps": statistics.mean(p["steps"] for p in plain),
        "success_at_most": 1 - len(unsolvable) / count, "unsolvable": unsolvable,
        "expert_success": sum(o["success"] for o in expert) / count,
        "expert_steps": statistics.mean(o["steps"] for o in expert),
        "labelled_states": labelled,
        # the labels the conflict rule executed unchanged (the rest it overrode)
        "labels_executed_rate": sum(o["labels_executed"] for o in expert) / max(labels, 1),
        "label_cpu_s_per_state": cpu / max(labelled, 1),
        "label_cpu_s_per_label": cpu / max(labels, 1),
        "label_wall_s_per_state": sum(o["label_seconds"] for o in expert) / max(calls, 1),
        "unlabelled_call_rate": sum(o["unsolved"] + o["too_long"] for o in expert)
        / max(calls, 1),
        "plans_per_episode": plans / count,
        "self_agreement": agree / pairs if pairs else None,
        "agreement_labels": pairs,
        "cpu_seconds": time.process_time() - began,
    }
    if log:
        log(_fmt(row))
    return row


def lifelong_row(cfg: DaggerConfig, task: dict, agents: int, count: int, log=None) -> dict:
    instances = ceiling_instances(task, agents, count, cfg.ceiling_seed)
    steps = task["max_steps"]
    seeds = [int(np.random.SeedSequence([cfg.ceiling_seed, k]).generate_state(1)[0])
             for k in range(count)]
    patience = cfg.anchor_patience
    plain = [play_lifelong(inst, steps, cfg.conflict_rule, s, anchor_patience=patience)
             for inst, s in zip(instances, seeds)]
    expert = [play_lifelong(inst, steps, cfg.conflict_rule, s, make_labeller(cfg), patience)
              for inst, s in zip(instances, seeds)]
    calls = sum(o["label_calls"] for o in expert)
    row = {"suite": _suite_name(task) + " lifelong", "kind": task["kind"], "size": task["size"],
           "agents": agents, "instances": count, "max_steps": steps, "rule": cfg.conflict_rule,
           "labeller": cfg.labeller,
           "pibt_throughput": statistics.mean(p["throughput"] for p in plain),
           "expert_throughput": statistics.mean(o["throughput"] for o in expert),
           "label_cpu_s_per_state": sum(o["label_cpu_seconds"] for o in expert)
           / max(calls, 1)}
    if log:
        log(_fmt(row))
    return row


def _fmt(row: dict) -> str:
    return " ".join(f"{k}={round(v, 4) if isinstance(v, float) else v}" for k, v in row.items())


def expert_ceiling(cfg: DaggerConfig, count: int | None = None, log=None) -> dict:
    """Every suite's row (module docstring); `count` overrides `ceiling_count`."""
    count = int(cfg.ceiling_count if count is None else count)
    lifelong_count = min(count, cfg.ceiling_lifelong_count)
    one_shot = [one_shot_row(cfg, task, n, count, log)
                for task in cfg.ceiling for n in task["agents"]]
    lifelong = [lifelong_row(cfg, task, n, lifelong_count, log)
                for task in cfg.ceiling_lifelong for n in task["agents"]]
    import os

    return {"labeller": cfg.labeller, "rule": cfg.conflict_rule,
            "anchor_patience": cfg.anchor_patience, "count": count,
            # the planners' budgets are wall clock: the machine's load says how much CPU they got
            "loadavg_at_end": list(os.getloadavg()),
            "lifelong_count": lifelong_count,
            "labeller_config": labeller_config(cfg), "one_shot": one_shot,
            "lifelong": lifelong}


def labeller_config(cfg: DaggerConfig) -> dict:
    if cfg.labeller in ("committed", "stuck"):
        out = {"committed_planner": cfg.committed_planner, "committed_budget": cfg.committed_budget,
               "committed_replan_every": cfg.committed_replan_every,
               "committed_swap": cfg.committed_swap,
               "committed_max_nodes": cfg.committed_max_nodes,
               "committed_follow_rule": cfg.committed_follow_rule,
               "committed_restarts": cfg.committed_restarts,
               "planner_seed": cfg.planner_seed}
        return {**out, "stuck_window": cfg.stuck_window} if cfg.labeller == "stuck" else out
    return {"label_time_limit": cfg.label_time_limit, "max_plan_factor": cfg.max_plan_factor,
            "max_plan_slack": cfg.max_plan_slack, "planner_seed": cfg.planner_seed}


def markdown(result: dict) -> str:
    """The ceiling as Markdown tables: one-shot success and steps, lifelong throughput."""
    lines = [f"labeller `{result['labeller']}` ({result['labeller_config']}) under "
             f"`{result['rule']}`, {result['count']} instances per row "
             f"({result['lifelong_count']} per lifelong row)", "",
             "| suite | agents | success at most | plain PIBT success | labeller success | "
             "plain PIBT steps | labeller steps | labels executed | self-agreement | "
             "CPU s / state | CPU s / label | unlabelled calls | plans / episode |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["one_shot"]:
        agreement = "-" if r["self_agreement"] is None else f"{r['self_agreement']:.2f}"
        lines.append(f"| {r['suite']} | {r['agents']} | {r.get('success_at_most', 1):.2f} | "
                     f"{r['pibt_success']:.2f} | "
                     f"{r['expert_success']:.2f} | {r['pibt_steps']:.1f} | "
                     f"{r['expert_steps']:.1f} | {r['labels_executed_rate']:.3f} | {agreement} | "
                     f"{r['label_cpu_s_per_state']:.4f} | {r['label_cpu_s_per_label']:.5f} | "
                     f"{r['unlabelled_call_rate']:.2f} | {r['plans_per_episode']:.1f} |")
    if result["lifelong"]:
        lines += ["", "| lifelong suite | agents | ticks | plain PIBT goals / tick | "
                  "labeller goals / tick | CPU s / state |", "|---|---|---|---|---|---|"]
        for r in result["lifelong"]:
            lines.append(f"| {r['suite']} | {r['agents']} | {r['max_steps']} | "
                         f"{r['pibt_throughput']:.3f} | {r['expert_throughput']:.3f} | "
                         f"{r['label_cpu_s_per_state']:.4f} |")
    return "\n".join(lines)
