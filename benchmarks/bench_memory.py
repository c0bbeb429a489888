"""Memory of the fleet's core over a long lifelong run, in one process: the evaluator's lifelong
rollout (`evaluation.lifelong.rollout`: observations, the policy's ranking, the conflict rule,
arrivals and next goals) of `--agents` agents on a generated map, printing the process's RSS
every `--every` seconds. A process that keeps running should level off.

    python benchmarks/bench_memory.py [--agents 128] [--size 40] [--steps 1500]
        [--checkpoint models/default.pt] [--no-padding] [--no-onednn]

--no-padding encodes DCC's inference batches at their own size (as before
`models.common.padded_rows`), --no-onednn turns oneDNN off (torch.backends.mkldnn).
"""

from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def rss_mb() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 // 2**20


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--agents", type=int, default=128)
    parser.add_argument("--size", type=int, default=40)
    parser.add_argument("--density", type=float, default=0.3)
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--checkpoint", default=str(REPO / "models" / "default.pt"))
    parser.add_argument("--rule", default="pibt_anchor_swap")
    parser.add_argument("--every", type=float, default=10.0, help="seconds between samples")
    parser.add_argument("--no-padding", action="store_true")
    parser.add_argument("--no-onednn", action="store_true")
    args = parser.parse_args()
    import torch

    from mapf_fleet.evaluation.lifelong import rollout
    from mapf_fleet.evaluation.policies import CheckpointBatchPolicy
    from mapf_fleet.fleet.instances import InstanceSource
    from mapf_fleet.fleet.run import FleetRun
    from mapf_fleet.fleet.tasks import LifelongTasks
    from mapf_fleet.models import dcc

    torch.set_num_threads(1)
    if args.no_onednn:
        torch.backends.mkldnn.enabled = False
    if args.no_padding:
        dcc.padded_rows = lambda rows: rows
    inst = InstanceSource(num_robots=args.agents, size=args.size, density=args.density,
                          seed=args.seed).load()
    run = FleetRun(inst.grid, inst.starts, LifelongTasks(grid=inst.grid, seed=args.seed),
                   inst.goals, rule=args.rule, max_steps=args.steps)
    policy = CheckpointBatchPolicy(args.checkpoint)
    started, done = time.monotonic(), threading.Event()

    def sample():
        while not done.wait(args.every):
            print(f"{time.monotonic() - started:6.0f} s  tick {run.tick:>6}  RSS {rss_mb():>6} MB",
                  flush=True)

    print(f"{args.agents} agents, {args.size}x{args.size}, {args.rule}, "
          f"padding {'off' if args.no_padding else 'on'}, oneDNN "
          f"{'off' if args.no_onednn else 'on'}; RSS {rss_mb()} MB at tick 0", flush=True)
    threading.Thread(target=sample, daemon=True).start()
    rollout(policy, [run], shielded=True)
    done.set()
    print(f"{time.monotonic() - started:6.0f} s  tick {run.tick:>6}  RSS {rss_mb():>6} MB (end)")


if __name__ == "__main__":
    main()
