"""Fleet throughput: lockstep ticks/s of `mapf-fleet up` for 8, 32 and 64 robots (separate
processes: one per robot up to 32, 64 as 8 processes x 8 nodes; and all in one process), beside
the batched evaluator's steps/s (MAPFEnv + network.step, one thread) on the same instance and
checkpoint, the compute limit. Startup (imports, discovery) is excluded: the simulator times
the ticks themselves.

    python benchmarks/bench_fleet.py [--checkpoint F] [--robots 8 32 64] [--steps 30]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time


def batched_steps_per_second(checkpoint, instance, steps):
    """Steps/s of the evaluator's own rollout (MAPFEnv + LearnedPolicy, one thread)."""
    import torch

    from mapf_fleet.grid.env import MAPFEnv
    from mapf_fleet.models.checkpoint import load_checkpoint
    from mapf_fleet.models.policy import LearnedPolicy

    torch.set_num_threads(1)
    model, _ = load_checkpoint(checkpoint)
    policy = LearnedPolicy(model, device="cpu")
    env = MAPFEnv(instance)
    obs, done, count = env.reset(), False, 0
    policy.reset(1, env.num_agents)
    start = time.perf_counter()
    while count < steps and not done:
        actions = policy.act(obs[None], env.positions[None])
        obs, _, done, _ = env.step(actions[0])
        count += 1
    return count / (time.perf_counter() - start)


def fleet_ticks_per_second(checkpoint, robots, size, seed, steps, layout, domain):
    record = os.path.join(tempfile.mkdtemp(prefix="bench_fleet_"), "run.json")
    cmd = [sys.executable, "-m", "mapf_fleet.cli", "up", "--checkpoint", checkpoint,
           "--num-robots", str(robots), "--size", str(size), "--seed", str(seed),
           "--max-steps", str(steps), "--record", record, "--quiet", "--domain-id", str(domain)]
    cmd += ["--single-process"] if layout == "one process" else [
        "--nodes-per-process", str(1 if robots <= 32 else 8)]
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    with open(record) as handle:
        run = json.load(handle)
    return run["steps"] / run["run_seconds"], run["missed_decisions"]


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--robots", type=int, nargs="+", default=[8, 32, 64])
    parser.add_argument("--size", type=int, default=40)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--layouts", nargs="+", default=["processes", "one process"])
    args = parser.parse_args()
    from mapf_fleet.grid.instance import generate_instance

    print(f"{'robots':>6} {'layout':<22} {'fleet ticks/s':>13} {'missed':>6} "
          f"{'batched steps/s':>15} {'ratio':>6}")
    domain = 120
    for robots in args.robots:
        instance = generate_instance(args.size, robots, 0.3, args.seed)
        limit = batched_steps_per_second(args.checkpoint, instance, args.steps)
        for layout in args.layouts:
            domain += 1
            name = layout if layout == "one process" else (
                f"{robots} processes" if robots <= 32 else f"{robots // 8} processes x 8")
            rate, missed = fleet_ticks_per_second(args.checkpoint, robots, args.size, args.seed,
                                                  args.steps, layout, domain)
            print(f"{robots:>6} {name:<22} {rate:>13.2f} {missed:>6} {limit:>15.1f} "
                  f"{rate / limit:>6.3f}", flush=True)


if __name__ == "__main__":
    main()
