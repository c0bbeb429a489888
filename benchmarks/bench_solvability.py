"""How many of the evaluator's generated instances can be solved at all: the project's LaCAM
(complete: a search that exhausts a region's configurations proves the region has no plan) from
the starts, successors by PIBT with swap, on the evaluator's `--kinds dense` / `--kinds maze`
instances (the same seeds and sides as `mapf-fleet evaluate`).

The generators place every goal in its agent's free region but do not check that the agents of
a region can pass each other: two agents in a dead-end corridor whose goals need them to pass
make an instance no method solves. So the success any method can reach on a suite is at most
1 - (proven unsolvable) / instances; this prints that bound beside the counts.

Per suite: instances, proven unsolvable (and which), solved within the node budget (and how many
of those plans fit the step limit), undecided (budget spent), the upper bound on success.

    .venv/bin/python benchmarks/bench_solvability.py [--kinds dense maze] [--sizes 21]
        [--agents 48 64] [--instances 100] [--seed 1] [--max-nodes 50000] [--json F]
"""

from __future__ import annotations

import argparse
import json
import time

from mapf_fleet.coordination.lacam import solvability
from mapf_fleet.evaluation.cli import dense_scenarios
from mapf_fleet.evaluation.protocol import ProtocolConfig, family_scenarios


def suites(args):
    out = []
    if "dense" in args.kinds:
        out += dense_scenarios(args.instances, args.seed, args.sizes, args.agents)
    rest = [k for k in args.kinds if k != "dense"]
    if rest:
        out += family_scenarios(ProtocolConfig.from_yaml(), rest, args.instances, args.seed,
                                args.sizes, args.agents)
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kinds", nargs="+", default=["dense", "maze"])
    parser.add_argument("--sizes", nargs="+", type=int, default=[21])
    parser.add_argument("--agents", nargs="+", type=int, default=[48, 64])
    parser.add_argument("--instances", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--max-nodes", type=int, default=50_000)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    print("| suite | agents | instances | proven unsolvable | solved (fit the step limit) | "
          "undecided | success at most | CPU s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    rows = []
    for scenario, instances in suites(args):
        began = time.process_time()
        kinds = {"unsolvable": [], "solved": [], "undecided": []}
        fits = 0
        for k in range(len(instances)):
            inst = instances.instance(k)
            kind, makespan = solvability(inst.grid, inst.starts, inst.goals, args.max_nodes)
            kinds[kind].append(k)
            fits += makespan is not None and makespan <= scenario.max_steps
        n = len(instances)
        row = {"suite": scenario.map_name, "agents": scenario.num_agents, "instances": n,
               "seed": args.seed, "max_steps": scenario.max_steps, "max_nodes": args.max_nodes,
               "unsolvable": kinds["unsolvable"], "solved": len(kinds["solved"]),
               "solved_within_limit": int(fits), "undecided": kinds["undecided"],
               "success_at_most": 1 - len(kinds["unsolvable"]) / n,
               "cpu_seconds": round(time.process_time() - began, 1)}
        rows.append(row)
        print(f"| {row['suite']} | {row['agents']} | {n} | {len(row['unsolvable'])} "
              f"{row['unsolvable']} | {row['solved']} ({fits}) | {len(row['undecided'])} | "
              f"{row['success_at_most']:.2f} | {row['cpu_seconds']} |", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"command": "benchmarks/bench_solvability.py", "args": vars(args),
                       "rows": rows}, f, indent=1)
    return {"rows": rows}


if __name__ == "__main__":
    main()
