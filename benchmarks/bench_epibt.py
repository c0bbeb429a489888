"""What EPIBT's longer horizon costs per tick: the one-step rule `pibt_anchor_swap` beside
`pibt_anchor_swap_epibt` (and other horizons), lifelong (an agent on its goal gets a new one), in
one process (issue 41's targets: <= 50 ms a tick at 64 agents, <= 1 s at 2,048 agents).

    python benchmarks/bench_epibt.py [--ticks 40] [--horizons 2 3 4] [--json OUT]
    python benchmarks/bench_epibt.py --waits [--instances 8] [--steps 256]

Per setting: random map of the side given, 20 % obstacles, distance rankings (plain PIBT's), the
median and the 95th percentile of the tick in milliseconds (ranking not included), wall clock and
the CPU time of the thread (what the tick costs on a core of its own when other processes load
the machine), and for EPIBT
the operations its search tried per agent (the bound is `epibt.TRIES_PER_AGENT`).

`--waits`: instead, lifelong throughput (the evaluator's runs and goal streams, heuristic
rankings, 64 agents on dense 21x21, maze 40x40, warehouse 40x40) of `pibt_anchor_swap_epibt`
with three ways of treating an operation that starts by waiting: `own` (the rule's: the agent's
own ranking stands), `plan` (the wait is ranked first like any EPIBT move), `stuck` (the own
ranking stands only where the whole operation waits).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mapf_fleet.coordination.epibt import EPIBTShield  # noqa: E402
from mapf_fleet.grid.actions import STAY  # noqa: E402
from mapf_fleet.coordination.factory import make_shield  # noqa: E402
from mapf_fleet.coordination.plan import distance_rankings  # noqa: E402
from mapf_fleet.coordination.rules import Rule  # noqa: E402
from mapf_fleet.grid.guidance_made import highways  # noqa: E402
from mapf_fleet.grid.maps import place_agents  # noqa: E402


ONE_STEP = "pibt_anchor_swap"  # the rule EPIBT extends (the fleet's rule until the `_lns` rules)


def tick_ms(blocked, agents, shield_of, ticks, seed) -> dict:
    rng = np.random.default_rng(seed)
    inst = place_agents(blocked.astype(np.uint8), agents, rng)
    shield = shield_of(inst.goals)
    free = np.argwhere(~blocked)
    positions = np.asarray(inst.starts)
    shield.step(positions, distance_rankings(shield, positions))  # distances searched
    times, cpu, tries = [], [], []
    for _ in range(ticks):
        prefs = distance_rankings(shield, positions)
        began, began_cpu = time.perf_counter(), time.thread_time()
        positions = shield.step(positions, prefs).positions
        times.append(time.perf_counter() - began)
        cpu.append(time.thread_time() - began_cpu)
        tries.append(getattr(shield, "tries", 0) / agents)
        arrived = (positions == shield.goals).all(axis=1)
        if arrived.any():  # lifelong: a new goal on arrival
            goals = shield.goals.copy()
            goals[arrived] = free[rng.integers(0, len(free), int(arrived.sum()))]
            shield.set_goals(goals)
    times.sort()
    cpu.sort()
    p95 = min(len(times) - 1, int(0.95 * len(times)))
    return {"median_ms": 1e3 * statistics.median(times), "p95_ms": 1e3 * times[p95],
            "cpu_median_ms": 1e3 * statistics.median(cpu), "cpu_p95_ms": 1e3 * cpu[p95],
            "tries_per_agent": statistics.mean(tries)}


class _WaitPolicy(EPIBTShield):
    """EPIBT with another treatment of an operation that starts by waiting (`--waits`)."""

    waits = "own"

    def _first_moves(self, positions, asked, fixed, reserved):
        paths, held = self._search(positions, asked, fixed, reserved)
        first = self._action_of_delta[paths[:, 1] - paths[:, 0] + self.width]
        if self.waits == "own":
            first = np.where(first == STAY, asked[:, 0], first)
        elif self.waits == "stuck":
            first = np.where((paths == paths[:, :1]).all(axis=1), asked[:, 0], first)
        return first, held


def wait_policies(instances: int, steps: int) -> list[dict]:
    from mapf_fleet.evaluation.lifelong import lifelong_instances, lifelong_runs, rollout
    from mapf_fleet.evaluation.policies import HeuristicBatchPolicy

    rows = []
    for kind, size in (("dense", 21), ("maze", 40), ("warehouse", 40)):
        made = lifelong_instances(kind, size, 64, instances, 0)
        for waits in ("own", "plan", "stuck"):
            runs = lifelong_runs(made, steps, "pibt_anchor_swap_epibt", 0)
            for run in runs:
                run.arbiter.shield.__class__ = type("Policy", (_WaitPolicy,), {"waits": waits})
            rollout(HeuristicBatchPolicy(), runs, shielded=True)
            tp = float(np.mean([run.goals_reached for run in runs])) / steps
            rows.append({"kind": kind, "size": size, "waits": waits, "throughput": tp})
            print(f"{kind} {size}x{size}, 64 agents, waits {waits}: throughput {tp:.3f}",
                  flush=True)
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--ticks", type=int, default=40)
    p.add_argument("--horizons", nargs="+", type=int, default=[2, 3, 4],
                   help="EPIBT horizons measured at 64 agents besides the rule's own")
    p.add_argument("--waits", action="store_true",
                   help="lifelong throughput of three treatments of a first wait instead")
    p.add_argument("--instances", type=int, default=8)
    p.add_argument("--steps", type=int, default=256)
    p.add_argument("--json")
    args = p.parse_args()
    if args.waits:
        rows = wait_policies(args.instances, args.steps)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))
        return 0
    epibt_rule = Rule.pibt(**Rule.parse(ONE_STEP).pibt_options(), epibt=True)
    rows = []
    for side, agents in ((21, 64), (32, 256), (128, 2048)):
        blocked = np.random.default_rng(1).random((side, side)) < 0.2
        for name, guidance in (("none", None), ("highways", highways(blocked))):
            settings = [(ONE_STEP, None), (epibt_rule.name, None)]
            if agents == 64:
                settings += [(epibt_rule.name, h) for h in args.horizons
                             if h != epibt_rule.horizon]
            for rule, horizon in settings:
                if horizon is None:
                    def shield_of(goals, rule=rule, guidance=guidance):
                        return make_shield(rule, blocked, goals, guidance=guidance)
                else:
                    def shield_of(goals, horizon=horizon, guidance=guidance):
                        return EPIBTShield(blocked, goals, **epibt_rule.pibt_options(),
                                           guidance=guidance, horizon=horizon)
                row = {"side": side, "agents": agents, "guidance": name, "rule": rule,
                       "horizon": horizon or Rule.parse(rule).horizon,
                       **tick_ms(blocked, agents, shield_of, args.ticks, 2)}
                rows.append(row)
                print(f"{side}x{side}, {agents} agents, guidance {name}, {rule} "
                      f"(horizon {row['horizon']}): median {row['median_ms']:.1f} ms, "
                      f"p95 {row['p95_ms']:.1f} ms (CPU time of the thread: median "
                      f"{row['cpu_median_ms']:.1f} ms, p95 {row['cpu_p95_ms']:.1f} ms), "
                      f"{row['tries_per_agent']:.1f} tries an agent", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
