"""The project's LaCAM from the starts, its successors by plain PIBT or by PIBT with swap
(`LaCAM(swap=True)`, lacam3's), and with restarts (the best of several seeds' plans), on the expert
ceiling's instances (`training.dagger.ceiling.ceiling_instances`, seed 0: the generated dense maps
17-21 cells and mazes 21x21, the evaluator's `--kinds` instances).

Per setting: plans found within the node budget, plans that fit the step limit (128), median
makespan of the plans found, CPU seconds and high-level nodes in all. A node budget (not wall
clock) bounds each search, so the figures do not depend on the machine's load.

    .venv/bin/python benchmarks/bench_lacam_successors.py [--kinds dense maze] [--agents 48 64]
        [--instances 20] [--max-nodes 50000] [--restarts 8]
"""

from __future__ import annotations

import argparse
import statistics
import time

from mapf_fleet.coordination.lacam import LaCAM, check_plan
from mapf_fleet.training.dagger.ceiling import ceiling_instances

STEP_LIMIT = 128


def run(instances, swap: bool, restarts: int, max_nodes: int) -> dict:
    found = fits = nodes = 0
    makespans = []
    began = time.process_time()
    for inst in instances:
        best = None
        for seed in range(restarts):
            result = LaCAM(inst.grid, seed=seed, swap=swap).plan(
                inst.starts, inst.goals, time_limit=3600.0, max_nodes=max_nodes)
            nodes += result.nodes
            if result.solved:
                assert check_plan(inst.grid, result.positions, inst.starts, inst.goals) == []
                length = len(result.positions) - 1
                best = length if best is None else min(best, length)
        if best is not None:
            found += 1
            fits += best <= STEP_LIMIT
            makespans.append(best)
    return {"found": found, "fits": fits, "makespan": statistics.median(makespans)
            if makespans else None, "cpu_s": time.process_time() - began, "nodes": nodes}


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--kinds", nargs="+", default=["dense", "maze"])
    parser.add_argument("--agents", nargs="+", type=int, default=[48, 64])
    parser.add_argument("--instances", type=int, default=20)
    parser.add_argument("--max-nodes", type=int, default=50_000)
    parser.add_argument("--restarts", type=int, default=8)
    args = parser.parse_args()
    print(f"| suite | agents | successors | searches | plans found | fit {STEP_LIMIT} steps | "
          f"median makespan | CPU s | nodes |")
    print("|---|---|---|---|---|---|---|---|---|")
    for kind in args.kinds:
        for agents in args.agents:
            if kind == "maze" and agents > 48:
                continue  # the ceiling's mazes hold 32 / 48
            instances = ceiling_instances({"kind": kind, "size": 21, "max_steps": STEP_LIMIT},
                                          agents, args.instances, 0)
            for swap, restarts in ((False, 1), (True, 1), (True, args.restarts)):
                r = run(instances, swap, restarts, args.max_nodes)
                name = "PIBT with swap" if swap else "PIBT"
                print(f"| {kind} 21 | {agents} | {name} | {restarts} | {r['found']}/{len(instances)} "
                      f"| {r['fits']}/{len(instances)} | {r['makespan']} | {r['cpu_s']:.1f} | "
                      f"{r['nodes']} |", flush=True)


if __name__ == "__main__":
    main()
