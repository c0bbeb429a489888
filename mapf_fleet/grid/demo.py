"""`mapf-fleet demo`: generate an instance and run the non-learned heuristic policy on it."""

from __future__ import annotations

import argparse

import numpy as np

from .env import EnvConfig, MAPFEnv
from .instance import generate_instance
from .policies import heuristic_policy


def run_episode(env: MAPFEnv) -> dict:
    obs = env.reset()
    collisions = 0
    done, info = False, {"success": False, "steps": 0}
    while not done:
        obs, _, done, info = env.step(heuristic_policy(obs))
        collisions += int(np.count_nonzero(info["collisions"]))
    return {"success": bool(info["success"]), "steps": int(info["steps"]), "collisions": collisions,
            "on_goal": int(np.count_nonzero(env.on_goal()))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mapf-fleet demo", description=__doc__)
    parser.add_argument("--size", type=int, default=40, help="map side length (default 40)")
    parser.add_argument("--agents", type=int, default=16, help="number of agents (default 16)")
    parser.add_argument("--density", type=float, default=0.3, help="obstacle density (default 0.3)")
    parser.add_argument("--seed", type=int, default=0, help="instance seed (default 0)")
    parser.add_argument("--max-steps", type=int, default=256, help="step limit (default 256)")
    args = parser.parse_args(argv)
    try:
        instance = generate_instance(args.size, args.agents, args.density, args.seed)
        env = MAPFEnv(instance, EnvConfig(max_steps=args.max_steps))
    except ValueError as exc:
        parser.error(str(exc))
    result = run_episode(env)
    print(f"map {args.size}x{args.size}, density {args.density}, {args.agents} agents, "
          f"seed {args.seed}, policy: heuristic (follow heuristic channels, stay when blocked)")
    print(f"success: {result['success']}")
    print(f"steps: {result['steps']}")
    print(f"collisions: {result['collisions']}")
    print(f"agents on goal: {result['on_goal']}/{args.agents}")
    return 0  # the demo ran; an unsuccessful episode is an outcome, not an error
