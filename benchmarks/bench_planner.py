"""Cost of the planning arbiter (`conflict_rule: lacam`): the planner per call, and per tick under
the plan keeper, one-shot and lifelong.

For each map size and fleet size (default 40x40 and 80x80 random maps, density 0.2 -- the
protocol's density 0.3 leaves too few free cells for 256 robots on 40x40 --, 32 / 64 / 128 / 256
robots; `--instances` per cell, generated from `--seed`):
- **planner call:** one `LaCAM.plan` from the starts with distance rankings and a budget of
  `--budget` seconds: solved fraction, median and max wall seconds, median nodes, median makespan;
- **one-shot under the keeper:** `PlanKeeper(planning_budget=--tick-budget)` steps the instance
  with plain PIBT's rankings until every robot is on its goal or `--steps` ticks: planner seconds
  per tick (mean, max), fallback rate, success;
- **lifelong under the keeper** (`--lifelong`): the lifelong task source (a new goal on arrival)
  for `--steps` ticks: the same counters and the goals reached per tick.
- **rankings A/B** (`--ab C ...`, e.g. `heuristic models/default.pt`): the evaluator's rollout
  (`run_decentralized`, `--conflict-rule lacam`) on the generated dense maps (`--kinds dense`, seed 0,
  `--instances` each of `--agents`), the planner's root step ranked by each policy's rankings:
  success, average steps, planner seconds per tick, fallback rate.
- **committed expert as the policy** (`--expert-under RULE ...`, e.g. `pibt pibt_anchor`): on
  the same dense maps, `CommittedExpert`'s labels (its next move first, then the distance order)
  go through the shield of each rule every tick: success, average steps, re-plans per episode.
Wall-clock seconds (the planner's budget is wall clock); run it niced on a quiet machine.

    .venv/bin/python benchmarks/bench_planner.py [--sizes 40 80] [--agents 32 64 128 256]
        [--instances 3] [--budget 5] [--tick-budget 1] [--steps 256] [--lifelong] [--json OUT]
    .venv/bin/python benchmarks/bench_planner.py --ab heuristic models/default.pt --agents 48 64
        --instances 20 --tick-budget 1
    .venv/bin/python benchmarks/bench_planner.py --expert-under pibt pibt_anchor --agents 48 64
        --instances 20 --tick-budget 1
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mapf_fleet.coordination.lacam import LaCAM, check_plan  # noqa: E402
from mapf_fleet.coordination.plan import PlanKeeper, distance_rankings  # noqa: E402
from mapf_fleet.grid.instance import generate_instance  # noqa: E402


def planner_call(inst, budget: float) -> dict:
    planner = LaCAM(inst.grid)
    planner.distances((inst.goals[:, 0] * inst.grid.shape[1] + inst.goals[:, 1]).tolist())
    result = planner.plan(inst.starts, inst.goals, time_limit=budget)
    if result.solved:
        assert check_plan(inst.grid, result.positions, inst.starts, inst.goals) == []
    return {"solved": result.solved, "seconds": result.seconds, "nodes": result.nodes,
            "makespan": len(result.positions) - 1 if result.solved else None}


def keeper_run(inst, tick_budget: float, steps: int, lifelong: bool, seed: int) -> dict:
    if lifelong:  # the lifelong rollout of the evaluator (fleet core, lifelong task source)
        from mapf_fleet.evaluation.lifelong import lifelong_runs, rollout
        from mapf_fleet.evaluation.policies import HeuristicBatchPolicy
        from mapf_fleet.evaluation.protocol import InstanceSet

        runs = lifelong_runs(InstanceSet.from_instances([inst], "bench"), steps, "lacam", seed,
                             planning_budget=tick_budget)
        rollout(HeuristicBatchPolicy(), runs, shielded=True)
        keeper = runs[0].arbiter.shield
        extra = {"throughput": runs[0].goals_reached / steps}
    else:
        keeper = PlanKeeper(inst.grid, inst.goals, planning_budget=tick_budget)
        positions = inst.starts.copy()
        done_at = None
        for t in range(steps):
            positions = keeper.step(positions, distance_rankings(keeper, positions)).positions
            if (positions == keeper.goals).all():
                done_at = t + 1
                break
        extra = {"success": done_at is not None, "steps": done_at or steps}
    s = keeper.stats()
    ticks = s["ticks"]
    return {"ticks": ticks, "planner_calls": s["planner_calls"],
            "planner_seconds_per_tick": s["planner_seconds"] / ticks,
            "planner_max_seconds": s["planner_max_seconds"],
            "tick_max_seconds": s["tick_max_seconds"],
            "fallback_rate": s["fallback_rate"], **extra}


def rankings_ab(policies, agents, count, tick_budget) -> list[dict]:
    from mapf_fleet.evaluation.cli import dense_scenarios
    from mapf_fleet.evaluation.policies import build_policy, parse_policy, with_conflict_rule
    from mapf_fleet.evaluation.runner import run_decentralized

    rows = []
    for scenario, instances in dense_scenarios(count, 0, agents=agents):
        for name in policies:
            spec = with_conflict_rule(parse_policy(name), "lacam")
            stats: list = []
            records = run_decentralized(build_policy(spec), instances, scenario.max_steps,
                                        "lacam", planning_budget=tick_budget, stats=stats)
            ticks = sum(s["ticks"] for s in stats)
            row = {"policy": spec.name, "ranking": spec.resolved_ranking,
                   "map": scenario.map_name, "agents": scenario.num_agents,
                   "success": sum(r.success for r in records) / len(records),
                   "average_steps": statistics.mean(r.steps for r in records),
                   "planner_s_per_tick": sum(s["planner_seconds"] for s in stats) / ticks,
                   "planner_max_s": max(s["planner_max_seconds"] for s in stats),
                   "planner_calls_per_episode": statistics.mean(s["planner_calls"] for s in stats),
                   "fallback_rate": sum(s["fallback_ticks"] for s in stats) / ticks}
            rows.append(row)
            print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v)
                              for k, v in row.items()}), flush=True)
    return rows


def expert_as_policy(rules, agents, count, tick_budget) -> list[dict]:
    from mapf_fleet.coordination.factory import make_shield
    from mapf_fleet.training.dagger.expert import CommittedExpert
    from mapf_fleet.evaluation.cli import dense_scenarios

    rows = []
    for scenario, instances in dense_scenarios(count, 0, agents=agents):
        for rule in rules:
            solved, steps, replans = 0, [], 0
            for k in range(len(instances)):
                inst = instances.instance(k)
                expert = CommittedExpert(inst.grid, inst.goals, planning_budget=tick_budget)
                shield = make_shield(rule, inst.grid, inst.goals)
                positions, done = inst.starts.copy(), None
                for t in range(scenario.max_steps):
                    labels = expert.moves(positions)
                    replans += expert.last["replanned"]
                    rest = distance_rankings(shield, positions)
                    prefs = np.array([[a] + [x for x in row if x != a]
                                      for a, row in zip(labels.tolist(), rest.tolist())])
                    positions = shield.step(positions, prefs).positions
                    if (positions == inst.goals).all():
                        done = t + 1
                        break
                solved += done is not None
                steps.append(done or scenario.max_steps)
            row = {"expert": "committed", "rule": rule, "map": scenario.map_name,
                   "agents": scenario.num_agents, "success": solved / len(instances),
                   "average_steps": statistics.mean(steps),
                   "replans_per_episode": replans / len(instances)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", nargs="+", type=int, default=[40, 80])
    p.add_argument("--agents", nargs="+", type=int, default=[32, 64, 128, 256])
    p.add_argument("--density", type=float, default=0.2)
    p.add_argument("--instances", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--budget", type=float, default=5.0, help="seconds per planner call")
    p.add_argument("--tick-budget", type=float, default=1.0, help="the keeper's planning_budget")
    p.add_argument("--steps", type=int, default=256)
    p.add_argument("--lifelong", action="store_true", help="also run the lifelong stream")
    p.add_argument("--no-keeper", action="store_true", help="planner calls only")
    p.add_argument("--ab", nargs="+", metavar="C",
                   help="rankings A/B on the dense maps with these policies instead")
    p.add_argument("--expert-under", nargs="+", metavar="RULE",
                   help="the committed expert as the policy under these rules instead")
    p.add_argument("--json", metavar="OUT")
    args = p.parse_args(argv)
    if args.expert_under:
        rows = expert_as_policy(args.expert_under, args.agents, args.instances, args.tick_budget)
        if args.json:
            Path(args.json).write_text(json.dumps({"argv": sys.argv, "rows": rows}, indent=1))
        return 0
    if args.ab:
        rows = rankings_ab(args.ab, args.agents, args.instances, args.tick_budget)
        if args.json:
            Path(args.json).write_text(json.dumps({"argv": sys.argv, "rows": rows}, indent=1))
        return 0
    rows = []
    for size in args.sizes:
        for n in args.agents:
            rng = np.random.default_rng([args.seed, size, n])
            instances = [generate_instance(size, n, args.density, rng)
                         for _ in range(args.instances)]
            calls = [planner_call(inst, args.budget) for inst in instances]
            row = {"size": size, "agents": n, "instances": len(instances),
                   "call_solved": sum(c["solved"] for c in calls) / len(calls),
                   "call_median_s": statistics.median(c["seconds"] for c in calls),
                   "call_max_s": max(c["seconds"] for c in calls),
                   "call_median_nodes": statistics.median(c["nodes"] for c in calls),
                   "call_median_makespan": statistics.median(
                       [c["makespan"] for c in calls if c["solved"]] or [float("nan")])}
            modes = [] if args.no_keeper else [False] + ([True] if args.lifelong else [])
            for lifelong in modes:
                runs = [keeper_run(inst, args.tick_budget, args.steps, lifelong, args.seed + k)
                        for k, inst in enumerate(instances)]
                key = "lifelong" if lifelong else "oneshot"
                ticks = sum(r["ticks"] for r in runs)
                row[f"{key}_planner_s_per_tick"] = sum(
                    r["planner_seconds_per_tick"] * r["ticks"] for r in runs) / ticks
                row[f"{key}_planner_max_s"] = max(r["planner_max_seconds"] for r in runs)
                row[f"{key}_tick_max_s"] = max(r["tick_max_seconds"] for r in runs)
                row[f"{key}_fallback_rate"] = sum(
                    r["fallback_rate"] * r["ticks"] for r in runs) / ticks
                row[f"{key}_planner_calls_per_tick"] = sum(r["planner_calls"] for r in runs) / ticks
                if lifelong:
                    row["lifelong_throughput"] = statistics.mean(r["throughput"] for r in runs)
                else:
                    row["oneshot_success"] = sum(r["success"] for r in runs) / len(runs)
                    row["oneshot_steps"] = statistics.mean(r["steps"] for r in runs)
            rows.append(row)
            print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v)
                              for k, v in row.items()}), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"argv": sys.argv, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
