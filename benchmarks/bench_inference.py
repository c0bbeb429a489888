"""Inference cost of DHC and DCC: milliseconds per agent step on one CPU thread.

Batched: one episode of N agents per `step` (N = 16, 64, 128 by default), on a 40x40 map with
uniformly random distinct positions (the paper's density of agents for 40x40 test instances),
observations synthetic but consistent with the positions. Per robot: each robot runs its own
split step (encode, communication, Q-values; DCC with its causal check) with the messages of
the others, as a ROS policy node would; the figure is the mean over the robots of one fleet.

Usage: .venv/bin/python benchmarks/bench_inference.py [--agents 16 64 128] [--repeats 10]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mapf_fleet.models import ModelConfig, build_model, dhc_partners, fov_neighbours  # noqa: E402
from mapf_fleet.models.synthetic import make_sensitive, random_positions, synthetic_obs  # noqa: E402


def fleet(seed: int, num_agents: int, side: int):
    rng = np.random.default_rng(seed)
    positions = random_positions(rng, num_agents, side)
    return synthetic_obs(rng, positions), positions


def time_batched(net, obs, positions, repeats: int) -> tuple[float, float]:
    """(median ms per agent step, mean requests per agent) over `repeats` consecutive steps."""
    obs_t, pos_t = torch.from_numpy(obs)[None], torch.from_numpy(positions)[None]
    hidden, last = None, None
    times, requests = [], []
    with torch.no_grad():
        for i in range(repeats + 2):
            extra = {"last_action": last} if net.config.algo == "dcc" else {}
            start = time.perf_counter()
            out = net.step(obs_t, pos_t, hidden, **extra)
            elapsed = time.perf_counter() - start
            hidden, last = out.hidden, out.actions
            if i >= 2:  # warm-up
                times.append(elapsed)
                requests.append(out.comm_mask.sum().item() / len(positions))
    return statistics.median(times) * 1e3 / len(positions), float(np.mean(requests))


def time_per_robot(net, obs, positions, repeats: int) -> float:
    """Median over steps of (total robot compute time / N), messages passed in memory."""
    n = len(positions)
    cfg = net.config
    hidden = [None] * n
    last = [-1] * n
    times = []
    with torch.no_grad():
        for i in range(repeats + 1):
            start = time.perf_counter()
            if cfg.algo == "dhc":
                partners = dhc_partners(positions, cfg.obs_radius, cfg.max_partners)
                h = [net.encode(obs[j], hidden[j]) for j in range(n)]
                for r in range(cfg.comm_rounds):
                    sent = list(h)
                    h = [net.comm_round(r, sent[j], [sent[p] for p in partners[j] if p >= 0])
                         for j in range(n)]
                final = h
            else:
                h, requested = [], []
                for j in range(n):
                    indices, offsets = fov_neighbours(positions, j, cfg.obs_radius)
                    h.append(net.encode(obs[j], last[j], hidden[j]))
                    requested.append(indices[net.causal_set(obs[j], last[j], hidden[j], offsets)])
                inbox = [[] for _ in range(n)]
                for j in range(n):
                    for k in requested[j]:
                        inbox[k].append((positions[j] - positions[k], h[j]))
                h1 = [net.aggregate_requests(h[j], inbox[j]) for j in range(n)]
                final = [net.aggregate_replies(h1[j], [(positions[k] - positions[j], h1[k])
                                                       for k in requested[j]]) for j in range(n)]
            actions = [int(net.q_values(v).argmax()) for v in final]
            elapsed = time.perf_counter() - start
            hidden, last = final, actions
            if i >= 1:
                times.append(elapsed)
    return statistics.median(times) * 1e3 / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[16, 64, 128])
    parser.add_argument("--per-robot-agents", type=int, default=16)
    parser.add_argument("--side", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--algos", nargs="+", default=["dhc", "dcc"])
    parser.add_argument("--presets", nargs="+", default=["paper", "small"])
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), map {args.side}x"
          f"{args.side}, random weights scaled so DCC communicates (synthetic.make_sensitive)")
    print(f"{'algo':5} {'preset':6} {'mode':10} {'agents':>6} {'ms/agent-step':>14} "
          f"{'requests/agent':>15}")
    for algo in args.algos:
        for preset in args.presets:
            net = make_sensitive(build_model(ModelConfig.preset(algo, preset)), 0).eval()
            for n in args.agents:
                obs, positions = fleet(n, n, args.side)
                ms, req = time_batched(net, obs, positions, args.repeats)
                req_text = f"{req:15.2f}" if algo == "dcc" else f"{'-':>15}"
                print(f"{algo:5} {preset:6} {'batched':10} {n:6d} {ms:14.3f} {req_text}", flush=True)
            n = args.per_robot_agents
            obs, positions = fleet(n, n, args.side)
            ms = time_per_robot(net, obs, positions, max(3, args.repeats // 3))
            print(f"{algo:5} {preset:6} {'per-robot':10} {n:6d} {ms:14.3f} {'-':>15}", flush=True)


if __name__ == "__main__":
    main()
