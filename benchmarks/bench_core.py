"""The batched core at scale: wall time per joint step of observations, inference and conflict
rule, one process, for thousands of agents (one-shot and lifelong).

One run of the fleet core (`fleet.run.FleetRun`, the core of the evaluator's lifelong rollout,
the simulator node and the aggregator) on a generated map (DHC protocol, density 0.3 by default),
stepped the way `evaluation.lifelong.rollout` steps it:

    observations  `evaluation.lifelong.observe_runs` (the FOV windows of every robot, with the
                  heuristic bits of its current goal: a BFS per new goal)
    inference     the policy's ranking (`CheckpointBatchPolicy.rank`: the network's batched step
                  and the Q ranking; `heuristic`: the distance ranking, i.e. plain PIBT)
    conflict rule `FleetRun.step`: the arbiter (PIBT distance tables per goal), arrivals and the
                  next goals of the lifelong source

Conflict rule: the fleet's default for DCC, `pibt` for the heuristic (plain PIBT), or `--rule`.
Times are wall clock (torch may use more than one thread: `--threads`), medians and means over
`--steps` steps after `--warmup` steps, with the CPU time of a step beside (the process's, less
sensitive to a shared machine's load); the first step (every goal's BFS) is printed apart, and
the process's peak memory (cumulative over the cases of one command).
Printed beside each case: the figures measured before this benchmark existed (`BEFORE`, named
constants with their source).

    .venv/bin/python benchmarks/bench_core.py [--case lifelong-2048 oneshot-10000 ...]
        [--policy dcc heuristic] [--steps 10] [--threads 2] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mapf_fleet.evaluation.lifelong import observe_runs  # noqa: E402
from mapf_fleet.evaluation.policies import (  # noqa: E402
    CheckpointBatchPolicy, HeuristicBatchPolicy,
)
from mapf_fleet.fleet.arbiter import DEFAULT_CONFLICT_RULE  # noqa: E402
from mapf_fleet.fleet.record import Decisions  # noqa: E402
from mapf_fleet.fleet.run import FleetRun  # noqa: E402
from mapf_fleet.fleet.tasks import InstanceTasks, LifelongTasks  # noqa: E402
from mapf_fleet.grid.instance import generate_instance  # noqa: E402

# name: (map side, agents, lifelong)
CASES = {
    "lifelong-64": (21, 64, True),  # issue 41's per-tick target: <= 50 ms at 64 agents
    "oneshot-2048": (256, 2048, False),
    "lifelong-2048": (256, 2048, True),
    "oneshot-10000": (512, 10000, False),
    "lifelong-10000": (512, 10000, True),
}

# Per-step figures reported before this benchmark (one process, one torch thread), quoted in
# docs/results.md "The core at scale": (case, policy) -> seconds per step in all.
BEFORE = {
    ("oneshot-2048", "dcc"): 0.603,
    ("oneshot-2048", "heuristic"): 0.0078,
    ("lifelong-2048", "dcc"): 3.4,
    ("lifelong-2048", "heuristic"): 6.5,
    ("oneshot-10000", "dcc"): 12.1,
    ("oneshot-10000", "heuristic"): 0.044,
}
BEFORE_SOURCE = "docs/results.md, 'The core at scale' (as reported before this benchmark)"


def make_policy(name: str, checkpoint: str):
    if name == "heuristic":
        return HeuristicBatchPolicy()
    return CheckpointBatchPolicy(checkpoint)


def run_case(case: str, policy_name: str, args) -> dict:
    side, agents, lifelong = CASES[case]
    inst = generate_instance(side, agents, args.density, args.seed)
    tasks = LifelongTasks(grid=inst.grid, seed=args.seed) if lifelong else InstanceTasks()
    rule = args.rule or ("pibt" if policy_name == "heuristic" else DEFAULT_CONFLICT_RULE)
    from mapf_fleet.grid.guidance_made import GuidanceSource

    source = GuidanceSource.parse(args.guidance)
    run = FleetRun(inst.grid, inst.starts, tasks, inst.goals, rule=rule,
                   max_steps=args.warmup + args.steps + 1,
                   guidance=source.for_map(inst.grid), flow=source.flow(inst.grid))
    policy = make_policy(policy_name, args.checkpoint)
    policy.reset(1, agents)
    observation = getattr(policy, "observation", "paper")
    parts = {"observations": [], "inference": [], "conflict_rule": [], "goal_changes": []}
    cpu = []
    every = []  # every step's wall time, warm-up included: the first ticks after a cold start
    first = None
    for step in range(args.warmup + args.steps):
        goals_before = run.goals.copy()
        c0, t0 = time.process_time(), time.perf_counter()
        obs = observe_runs([run], observation)
        t1 = time.perf_counter()
        prefs = policy.rank(obs, run.positions[None], run.tick)
        t2 = time.perf_counter()
        result, _ = run.step(Decisions.complete(run.tick, prefs[0]))
        policy.executed(result.actions[None])
        t3, c3 = time.perf_counter(), time.process_time()
        split = {"observations": t1 - t0, "inference": t2 - t1, "conflict_rule": t3 - t2}
        every.append(round(t3 - t0, 3))
        if step == 0:
            first = split
        if step >= args.warmup:
            for key, value in split.items():
                parts[key].append(value)
            cpu.append(c3 - c0)
            parts["goal_changes"].append(int((run.goals != goals_before).any(axis=1).sum()))
    total = [sum(v) for v in zip(parts["observations"], parts["inference"],
                                 parts["conflict_rule"])]
    row = {"case": case, "policy": policy_name, "side": side, "agents": agents,
           "density": args.density, "lifelong": lifelong, "rule": rule,
           "guidance": source.label,
           "steps": args.steps, "threads": args.threads,
           "first_step_s": round(sum(first.values()), 4),
           "first_step_split_s": {k: round(v, 3) for k, v in first.items()},
           "every_step_s": every,
           "median_s": {k: round(statistics.median(v), 4) for k, v in parts.items()
                        if k != "goal_changes"},
           "mean_s": {k: round(statistics.fmean(v), 4) for k, v in parts.items()
                      if k != "goal_changes"},
           "step_median_s": round(statistics.median(total), 4),
           "step_mean_s": round(statistics.fmean(total), 4),
           "step_cpu_median_s": round(statistics.median(cpu), 4),
           "goal_changes_per_step": round(statistics.fmean(parts["goal_changes"]), 1),
           "goals_reached": run.goals_reached,
           "max_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
           "before_s": BEFORE.get((case, policy_name))}
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--case", nargs="+", default=["lifelong-2048", "oneshot-10000"],
                   choices=list(CASES))
    p.add_argument("--policy", nargs="+", default=["dcc", "heuristic"],
                   choices=["dcc", "heuristic"], help="dcc: --checkpoint; heuristic: plain PIBT")
    p.add_argument("--checkpoint", default=str(ROOT / "models" / "default.pt"))
    p.add_argument("--rule", help="conflict rule (default: the fleet's default for dcc, pibt for "
                                  "heuristic, i.e. plain PIBT)")
    p.add_argument("--density", type=float, default=0.3)
    p.add_argument("--guidance", default="none",
                   help="guidance graph of the run (GuidanceSource spelling: none, highways, "
                        "congestion, a file or model); none: BFS steps, this benchmark's "
                        "figures so far")
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--warmup", type=int, default=5,
                   help="steps before the timed ones (the first searches every goal; the "
                        "conflict rule's swap searches its neighbours' goals over the next ones)")
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", metavar="OUT")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    rows = []
    print(f"{'case':15s} {'policy':9s} {'rule':17s} {'obs ms':>8s} {'infer ms':>9s} {'rule ms':>8s} "
          f"{'step ms':>8s} {'mean ms':>8s} {'cpu ms':>7s} {'first s':>8s} {'new goals':>9s} "
          f"{'before ms':>9s} {'rss MB':>7s}")
    for case in args.case:
        for policy_name in args.policy:
            row = run_case(case, policy_name, args)
            rows.append(row)
            m = row["median_s"]
            before = "-" if row["before_s"] is None else f"{1e3 * row['before_s']:.0f}"
            print(f"{case:15s} {policy_name:9s} {row['rule']:17s} {1e3 * m['observations']:8.1f} "
                  f"{1e3 * m['inference']:9.1f} {1e3 * m['conflict_rule']:8.1f} "
                  f"{1e3 * row['step_median_s']:8.1f} {1e3 * row['step_mean_s']:8.1f} "
                  f"{1e3 * row['step_cpu_median_s']:7.1f} "
                  f"{row['first_step_s']:8.2f} {row['goal_changes_per_step']:9.1f} "
                  f"{before:>9s} {row['max_rss_mb']:7d}", flush=True)
            print(f"{'':15s} guidance {row['guidance']}; first step: " + ", ".join(
                f"{k} {v:.2f} s" for k, v in row["first_step_split_s"].items()), flush=True)
            print(f"{'':15s} every step, s: " + " ".join(f"{v:.2f}" for v in row["every_step_s"]),
                  flush=True)
    print(f"before: {BEFORE_SOURCE}")
    if args.json:
        Path(args.json).write_text(json.dumps({"command": " ".join(sys.argv),
                                               "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
