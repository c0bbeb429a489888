"""Per-step cost of each PIBT conflict rule (`coordination.rules.COORDINATED_RULES`: plain, anchor,
swap, hindrance and their combinations) at a few fleet sizes.

For each fleet size N (default 64 and 256) one crowded instance (the published 40x40 DHC test set
where it exists for N, else a generated 80x80 map of density 0.3) is played for `--steps` joint
steps under each rule with plain PIBT's rankings (BFS distance order, ties by the per-tick hash,
as the `heuristic` policy ranks); only `PIBTShield.step` is timed, in CPU seconds of this thread
(time.thread_time), so other processes on the machine do not inflate the figures. The first step
(BFS distance maps) is left out. Printed: median and 90th percentile ms per joint step, the ratio
to plain `pibt` of the same N, and the agents on goal at the end (the same instance and steps
for every rule).

    .venv/bin/python benchmarks/bench_pibt_variants.py [--agents 64 256] [--steps 100]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mapf_fleet.coordination.factory import make_shield  # noqa: E402
from mapf_fleet.coordination.rules import COORDINATED_RULES  # noqa: E402
from mapf_fleet.coordination.ranking import tie_breakers  # noqa: E402
from mapf_fleet.grid.instance import generate_instance, load_dhc_testset  # noqa: E402

TESTSETS = ROOT.parent / "shared" / "data" / "dhc_testsets"


def instance_for(num_agents: int, seed: int):
    published = TESTSETS / f"40length_{num_agents}agents.npz"
    if published.exists():
        return load_dhc_testset(published)[seed], "40x40 published"
    return generate_instance(80, num_agents, 0.3, seed), "80x80 generated"


def distance_rankings(shield, dist: np.ndarray, positions: np.ndarray, tick: int) -> np.ndarray:
    """(N, 5) plain PIBT's rankings: closer first, blocked moves last, ties by the tick's hash."""
    n = len(positions)
    cells = positions[:, 0] * shield.width + positions[:, 1]
    targets = shield._targets[cells]  # (N, 5) flat cells, -1 blocked
    reach = dist[np.arange(n)[:, None], np.maximum(targets, 0)]
    key = np.where((targets >= 0) & (reach >= 0), reach, np.iinfo(np.int64).max).astype(float)
    ties = tie_breakers(np.arange(n), tick)
    return np.lexsort((ties, key), axis=-1).astype(np.int64)


def measure(rule: str, instance, steps: int) -> tuple[list[float], int]:
    shield = make_shield(rule, instance.grid, instance.goals)
    dist = np.stack([shield.distance_map(i) for i in range(instance.num_agents)])
    positions = np.asarray(instance.starts)
    times = []
    for t in range(steps):
        prefs = distance_rankings(shield, dist, positions, t)
        a = time.thread_time()
        positions = shield.step(positions, prefs).positions
        times.append(time.thread_time() - a)
    on_goal = int((positions == np.asarray(instance.goals)).all(axis=1).sum())
    return times[1:], on_goal


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--agents", nargs="+", type=int, default=[64, 256])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rules", nargs="+", default=list(COORDINATED_RULES), choices=COORDINATED_RULES)
    args = parser.parse_args(argv)
    print(f"{args.steps} joint steps per rule, plain PIBT's rankings, CPU ms of "
          f"PIBTShield.step per joint step, one thread")
    print(f"{'agents':>6}  {'instance':<16} {'rule':<28} {'median':>8} {'p90':>8} "
          f"{'x pibt':>7} {'on goal':>8}")
    for n in args.agents:
        instance, kind = instance_for(n, args.seed)
        base = None
        for rule in args.rules:
            times, on_goal = measure(rule, instance, args.steps)
            med = 1e3 * statistics.median(times)
            p90 = 1e3 * float(np.percentile(times, 90))
            base = med if base is None else base
            print(f"{n:>6}  {kind:<16} {rule:<28} {med:>8.3f} {p90:>8.3f} {med / base:>7.2f} "
                  f"{on_goal:>5}/{n}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
