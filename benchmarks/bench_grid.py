"""Grid-world speed: reset time and agent-steps/s (step + observe) on one core.

Run: .venv/bin/python benchmarks/bench_grid.py [--steps 2000] [--policy random|heuristic]

reset = MAPFEnv construction + reset on a fresh instance with a cold heuristic cache (BFS for
every goal, padding, first observation); instance generation is timed separately.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from mapf_fleet.grid.batch_env import BatchMAPFEnv  # noqa: E402
from mapf_fleet.grid.env import EnvConfig, MAPFEnv  # noqa: E402
from mapf_fleet.grid.heuristic import HeuristicCache  # noqa: E402
from mapf_fleet.grid.instance import generate_instance  # noqa: E402
from mapf_fleet.grid.policies import heuristic_policy  # noqa: E402

CASES = ((40, 16), (40, 64), (80, 128))


def bench_case(size: int, agents: int, steps: int, policy: str, repeats: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    gen_times, reset_times = [], []
    env = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        instance = generate_instance(size, agents, 0.3, rng)
        t1 = time.perf_counter()
        env = MAPFEnv(instance, EnvConfig(max_steps=10**9), heuristic_cache=HeuristicCache())
        t2 = time.perf_counter()
        gen_times.append(t1 - t0)
        reset_times.append(t2 - t1)
    obs = env.reset()
    actions_rng = np.random.default_rng(seed + 1)
    random_actions = actions_rng.integers(0, 5, size=(steps, agents))
    start, cpu_start = time.perf_counter(), time.process_time()
    for k in range(steps):
        actions = heuristic_policy(obs) if policy == "heuristic" else random_actions[k]
        obs, _, done, _ = env.step(actions)
        if done:
            obs = env.reset()
    elapsed = time.perf_counter() - start
    cpu = time.process_time() - cpu_start
    return {"generate": float(np.median(gen_times)), "reset": float(np.median(reset_times)),
            "agent_steps_per_s": steps * agents / elapsed, "step_ms": 1e3 * elapsed / steps,
            "agent_steps_per_cpu_s": steps * agents / cpu}


def bench_batch(size: int, agents: int, episodes: int, steps: int, seed: int) -> dict:
    """BatchMAPFEnv: `episodes` instances stepped together with random actions."""
    rng = np.random.default_rng(seed)
    instances = [generate_instance(size, agents, 0.3, rng) for _ in range(episodes)]
    t0 = time.perf_counter()
    env = BatchMAPFEnv(instances, EnvConfig(max_steps=10**9), heuristic_cache=HeuristicCache())
    reset = time.perf_counter() - t0
    actions = rng.integers(0, 5, size=(steps, episodes, agents))
    start = time.perf_counter()
    for k in range(steps):
        env.step(actions[k])
    elapsed = time.perf_counter() - start
    return {"reset": reset, "agent_steps_per_s": steps * episodes * agents / elapsed,
            "step_ms": 1e3 * elapsed / steps}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=5, help="instances timed for reset")
    parser.add_argument("--policy", choices=("random", "heuristic"), default="random")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(f"policy={args.policy} steps={args.steps} (median of {args.repeats} resets, cold cache)")
    print("agent-steps/s = wall clock; per CPU-s = process CPU time (fairer on a shared machine)")
    print(f"{'case':>12} {'generate s':>11} {'reset s':>9} {'step ms':>8} {'agent-steps/s':>14} "
          f"{'per CPU-s':>10}")
    for size, agents in CASES:
        r = bench_case(size, agents, args.steps, args.policy, args.repeats, args.seed)
        print(f"{size}x{size}/{agents:<4} {r['generate']:>11.4f} {r['reset']:>9.4f} "
              f"{r['step_ms']:>8.3f} {r['agent_steps_per_s']:>14,.0f} "
              f"{r['agent_steps_per_cpu_s']:>10,.0f}")
    print("BatchMAPFEnv (random actions, reset = all episodes, cold cache):")
    for size, agents, episodes in ((40, 4, 200), (40, 16, 50), (80, 128, 4)):
        r = bench_batch(size, agents, episodes, max(args.steps // 4, 50), args.seed)
        print(f"{size}x{size}/{agents:<4} x{episodes:<4} reset {r['reset']:.4f} s, "
              f"step {r['step_ms']:.3f} ms, {r['agent_steps_per_s']:,.0f} agent-steps/s")


if __name__ == "__main__":
    main()
