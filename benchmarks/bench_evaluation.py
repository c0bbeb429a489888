"""Wall time of the full paper protocol (11 scenarios x 200 instances) on this machine, one core.

Measured on a fraction and extrapolated, because a full run with a paper-size network takes
hours here:
- learned policies (random weights, paper-size and small DHC): each scenario is run on K
  instances (at least --min-batch-agents agents per batched step, as the evaluator's batches of
  200 episodes are larger still) for S1 and for S2 steps; the difference gives the cost per
  batched step, the rest the setup (environments, heuristic channels). Random weights never
  solve an episode, so every episode runs to the limit: full = 200/K * (setup + limit * per_step).
- references (heuristic policy, LaCAM): K instances run to the end, times 200/K.

    .venv/bin/python benchmarks/bench_evaluation.py [--instances K] [--policies heuristic lacam small paper]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

import torch  # noqa: E402

from mapf_fleet.evaluation.policies import build_policy, parse_policy  # noqa: E402
from mapf_fleet.evaluation.protocol import ProtocolConfig, protocol_scenarios, scenario_instances  # noqa: E402
from mapf_fleet.evaluation.random_checkpoint import save_random_checkpoint  # noqa: E402
from mapf_fleet.evaluation.runner import run_decentralized, run_planner  # noqa: E402


def timed(fn, *args):
    began = time.perf_counter()
    out = fn(*args)
    return time.perf_counter() - began, out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--instances", type=int, default=2, help="instances measured per scenario (K)")
    parser.add_argument("--steps", type=int, nargs=2, default=(2, 8), metavar=("S1", "S2"))
    parser.add_argument("--min-batch-agents", type=int, default=512,
                        help="learned policies: K grows so that K x agents reaches this")
    parser.add_argument("--policies", nargs="+", default=["heuristic", "lacam", "small", "paper"])
    parser.add_argument("--sizes", nargs="+", type=int)
    args = parser.parse_args()
    torch.set_num_threads(1)

    config = ProtocolConfig.from_yaml()
    scenarios = protocol_scenarios(config, args.sizes)
    tmp = Path(tempfile.mkdtemp(prefix="bench_eval_"))
    names = {"small": ("dhc", "small"), "paper": ("dhc", "paper")}
    s1, s2 = args.steps
    print(f"# full protocol ({len(scenarios)} scenarios x {config.instances} instances), 1 core, torch threads 1")
    print(f"# references measured on {args.instances} instance(s) per scenario; learned policies on "
          f">= {args.min_batch_agents} agents per step, {s1} and {s2} steps; all extrapolated to {config.instances}")
    totals = {}
    for name in args.policies:
        if name in names:
            algo, preset = names[name]
            path = save_random_checkpoint(tmp / f"{algo}_{preset}.pt", algo, preset, seed=0)
            spec = replace(parse_policy(str(path)), name=f"DHC {preset} (random weights)")
        else:
            spec = parse_policy(name, planner_time_limit=config.planner_time_limit)
        policy = build_policy(spec)
        total = 0.0
        print(f"\n## {spec.name}")
        print("| scenario | instances measured | measured | full (200 instances) |")
        print("|---|---:|---:|---:|")
        for scenario in scenarios:
            count = args.instances
            if spec.kind == "checkpoint":
                count = min(config.instances, max(count, -(-args.min_batch_agents // scenario.num_agents)))
            instances = scenario_instances(scenario, count, density=config.density, seed=config.seed)
            scale = config.instances / len(instances)
            if spec.kind == "checkpoint":
                t1, _ = timed(run_decentralized, policy, instances, s1)
                t2, _ = timed(run_decentralized, policy, instances, s2)
                per_step = max(t2 - t1, 0.0) / (s2 - s1)
                setup = max(t1 - s1 * per_step, 0.0)
                full = scale * (setup + scenario.max_steps * per_step)
                agent_steps = len(instances) * scenario.num_agents
                measured = f"{per_step / agent_steps * 1e3:.3f} ms/agent-step, setup {setup:.2f} s"
            elif spec.is_planner:
                took, _ = timed(run_planner, policy, instances, scenario.max_steps)
                full, measured = scale * took, f"{took:.2f} s"
            else:
                took, _ = timed(run_decentralized, policy, instances, scenario.max_steps)
                full, measured = scale * took, f"{took:.2f} s"
            total += full
            print(f"| {scenario.key} | {len(instances)} | {measured} | {full:.0f} s |", flush=True)
        totals[spec.name] = total
        print(f"| **total** | | | **{total:.0f} s = {total / 3600:.2f} h** |")
    print("\n## summary: full protocol wall time on one core (divide by --workers up to the core count)")
    for name, total in totals.items():
        print(f"- {name}: {total:.0f} s ({total / 3600:.2f} h)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
