"""What the windowed plan costs per tick, and what its settings buy: `pibt_anchor_swap` beside
`pibt_anchor_swap_lns` (the fleet's rule), lifelong, in one process (issue 41's targets: <= 50 ms
a tick at 64 agents, <= 1 s at 2,048 agents).

    python benchmarks/bench_lns.py [--ticks 40] [--json OUT]
    python benchmarks/bench_lns.py --settings 8,64,8 16,128,8 [--instances 8] [--agents 64]

Per map (random, 20 % obstacles: 21x21 with 64 agents, 32x32 with 256, 128x128 with 2,048) and
guidance (none, highways): the median and 95th percentile of the tick in milliseconds, wall clock
and CPU time of the thread (`bench_epibt.tick_ms`: distance rankings, a new goal on arrival).

`--settings WINDOW,REPAIRS,GROUP ...`: instead, lifelong throughput inside POGEMA (the random
maps and mazes of `evaluation.pogema_bench`, the first `--instances`, no guidance) of
`pibt_anchor_swap_lns` with each setting of `rules.LNS_WINDOW`, `LNS_ITERATIONS` and
`LNS_NEIGHBOURHOOD` (set in this process for the run).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_epibt import tick_ms  # noqa: E402

from mapf_fleet.coordination import rules  # noqa: E402
from mapf_fleet.coordination.factory import make_shield  # noqa: E402
from mapf_fleet.grid.guidance_made import highways  # noqa: E402

ONE_STEP, PLANNED = "pibt_anchor_swap", "pibt_anchor_swap_lns"
SETTINGS = ("LNS_WINDOW", "LNS_ITERATIONS", "LNS_NEIGHBOURHOOD")


def settings_rows(settings: list[str], instances: int, agents: int) -> list[dict]:
    from mapf_fleet.evaluation import pogema_bench

    rows = []
    for spec in settings:
        values = [int(v) for v in spec.split(",")]
        if len(values) != 3:
            raise SystemExit(f"--settings: WINDOW,REPAIRS,GROUP, got {spec!r}")
        for name, value in zip(SETTINGS, values):
            setattr(rules, name, value)  # read by each shield when it is built
        out = Path(f"/tmp/bench_lns_{'_'.join(map(str, values))}.json")
        pogema_bench.main(["--mode", "lifelong", "--instances", str(instances), "--conflict-rule",
                           PLANNED, "--family", "random", "mazes", "--agents", str(agents),
                           "--guidance", "none", "--out", str(out)])
        for row in json.loads(out.read_text())["rows"]:
            rows.append({"window": values[0], "repairs": values[1], "group": values[2],
                         **{k: row[k] for k in ("family", "agents", "figure", "cpu_ms_per_tick")}})
            print(f"window {values[0]}, repairs {values[1]}, group {values[2]}: "
                  f"{row['family']} {row['agents']}: {row['figure']:.3f} goals a step, "
                  f"{row['cpu_ms_per_tick']:.1f} ms a tick (CPU)", flush=True)
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--ticks", type=int, default=40)
    p.add_argument("--settings", nargs="+", metavar="W,R,G",
                   help="lifelong throughput inside POGEMA per setting instead")
    p.add_argument("--instances", type=int, default=8)
    p.add_argument("--agents", type=int, default=64)
    p.add_argument("--json")
    args = p.parse_args()
    if args.settings:
        rows = settings_rows(args.settings, args.instances, args.agents)
    else:
        rows = []
        for side, agents in ((21, 64), (32, 256), (128, 2048)):
            blocked = np.random.default_rng(1).random((side, side)) < 0.2
            for name, guidance in (("none", None), ("highways", highways(blocked))):
                for rule in (ONE_STEP, PLANNED):
                    def shield_of(goals, rule=rule, guidance=guidance):
                        return make_shield(rule, blocked, goals, guidance=guidance)

                    row = {"side": side, "agents": agents, "guidance": name, "rule": rule,
                           **tick_ms(blocked, agents, shield_of, args.ticks, 2)}
                    row.pop("tries_per_agent")
                    rows.append(row)
                    print(f"{side}x{side}, {agents} agents, guidance {name}, {rule}: median "
                          f"{row['median_ms']:.1f} ms, p95 {row['p95_ms']:.1f} ms (CPU time of "
                          f"the thread: median {row['cpu_median_ms']:.1f} ms, p95 "
                          f"{row['cpu_p95_ms']:.1f} ms)", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
