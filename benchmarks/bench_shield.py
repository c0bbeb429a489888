"""Cost of the coordination layer (PIBT shield) per joint step, beside the policy's inference.

For each fleet size N (default 16, 64, 128, 512) one instance of the paper's protocol kind
(40x40 published DHC test set up to 64 agents, a generated 80x80 density 0.3 map above) is
played for `--steps` joint steps by a checkpoint under the shield, the way the evaluator does
it: one batched inference step for the fleet (`LearnedPolicy.act`), the preference orders
(`coordination.ranking.rank_actions`), then `PIBTShield.step`. Each part is timed in CPU
seconds of this thread (time.thread_time; torch runs on this one thread), so other processes on
the machine do not inflate the figures. Printed: median ms per joint step of inference, of the
ranking and of the shield, and the shield's share of one inference step.

Targets: shield at most 0.3 ms per joint step at 64 agents on one core, and at most
10 % of one inference step at every count.

    .venv/bin/python benchmarks/bench_shield.py [--agents 16 64 128 512] [--steps 64]
        [--checkpoint models/default.pt]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mapf_fleet.coordination.pibt import PIBTShield  # noqa: E402
from mapf_fleet.coordination.ranking import rank_actions, tie_breakers  # noqa: E402
from mapf_fleet.grid.env import EnvConfig, MAPFEnv  # noqa: E402
from mapf_fleet.grid.instance import generate_instance, load_dhc_testset  # noqa: E402
from mapf_fleet.models.checkpoint import load_checkpoint  # noqa: E402
from mapf_fleet.models.policy import LearnedPolicy  # noqa: E402

TESTSETS = ROOT.parent / "shared" / "data" / "dhc_testsets"


def instance_for(num_agents: int, seed: int):
    published = TESTSETS / f"40length_{num_agents}agents.npz"
    if published.exists():
        return load_dhc_testset(published)[seed], "40x40 published"
    return generate_instance(80, num_agents, 0.3, seed), "80x80 generated"


def measure(policy: LearnedPolicy, instance, steps: int) -> dict[str, list[float]]:
    env = MAPFEnv(instance, EnvConfig(max_steps=10**6, observation=policy.observation))
    obs = env.reset()
    shield = PIBTShield(instance.grid, instance.goals)
    policy.reset(1, instance.num_agents)
    ids = np.arange(instance.num_agents)
    times = {"inference": [], "ranking": [], "shield": []}
    for t in range(steps):
        a = time.thread_time()
        policy.act(obs[None], env.positions[None])
        b = time.thread_time()
        prefs = rank_actions(obs, policy.q_values[0], "q", ties=tie_breakers(ids, t))
        c = time.thread_time()
        result = shield.step(env.positions, prefs)
        d = time.thread_time()
        policy.set_last_actions(result.actions[None])
        obs, _, done, _ = env.step(result.actions)
        times["inference"].append(b - a)
        times["ranking"].append(c - b)
        times["shield"].append(d - c)
        if done:  # all on goal: start the same instance again to keep measuring a crowd
            obs = env.reset()
            shield.reset()
            policy.reset(1, instance.num_agents)
    return times


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--agents", nargs="+", type=int, default=[16, 64, 128, 512])
    parser.add_argument("--steps", type=int, default=64)
    parser.add_argument("--checkpoint", default=str(ROOT / "models" / "default.pt"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    model, metadata = load_checkpoint(args.checkpoint)
    policy = LearnedPolicy(model, device="cpu")
    print(f"checkpoint {args.checkpoint} ({model.config.algo}), {args.steps} joint steps per "
          f"fleet, CPU ms per joint step (median), one thread")
    print(f"{'agents':>6}  {'instance':<16} {'inference':>10} {'ranking':>12} {'shield':>8} "
          f"{'shield/inference':>17}")
    for n in args.agents:
        instance, kind = instance_for(n, args.seed)
        times = measure(policy, instance, args.steps + 2)
        med = {k: 1e3 * statistics.median(v[2:]) for k, v in times.items()}  # 2 warm-up steps
        share = med["shield"] / med["inference"]
        print(f"{n:>6}  {kind:<16} {med['inference']:>10.3f} {med['ranking']:>12.3f} "
              f"{med['shield']:>8.3f} {100 * share:>16.1f}%")
    print("targets: shield <= 0.3 ms at 64 agents; shield <= 10% of inference at "
          "every count")
    return 0


if __name__ == "__main__":
    sys.exit(main())
