"""Inference cost of DHC and DCC: milliseconds per agent step on one CPU thread.

Batched: one episode of N agents per `step` (N = 16, 64, 128 by default) with uniformly random
distinct positions on the map of the paper's test protocol for that fleet size (40x40 up to 64
agents, 80x80 above), observations synthetic but consistent with the positions. DCC's cost
grows with the number of FOV neighbours (one extra encoder pass per neighbour), printed too.
Per robot: the fleet's exchange (`models.exchange.LinkedExchanges`) with each robot alone in
its "process" (a thread here), messages passed in memory, as the ROS fleet with one robot per
process computes (encode, communication, Q-values; DCC with its causal check); the figure is
the mean over the robots of one fleet.

Times are CPU time (batched: of the calling thread, time.thread_time, torch uses that one
thread; per robot: of the process, time.process_time, over the robots' threads), so other
processes on a shared machine do not inflate them; the wall-clock median is shown beside.

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

from mapf_fleet.models import ModelConfig, build_model  # noqa: E402
from mapf_fleet.models.exchange import LinkedExchanges  # noqa: E402
from mapf_fleet.models.synthetic import (  # noqa: E402
    make_sensitive, random_positions, synthetic_obs,
)


def fleet(seed: int, num_agents: int, side: int):
    rng = np.random.default_rng(seed)
    positions = random_positions(rng, num_agents, side)
    return synthetic_obs(rng, positions), positions


def time_batched(net, obs, positions, repeats: int) -> tuple[float, float, float]:
    """(median CPU ms, median wall ms per agent step, mean requests per agent) over `repeats`
    consecutive steps with the hidden state carried."""
    obs_t, pos_t = torch.from_numpy(obs)[None], torch.from_numpy(positions)[None]
    hidden, last = None, None
    cpu, wall, requests = [], [], []
    with torch.no_grad():
        for i in range(repeats + 2):
            extra = {"last_action": last} if net.config.algo == "dcc" else {}
            start, start_wall = time.thread_time(), time.perf_counter()
            out = net.step(obs_t, pos_t, hidden, **extra)
            cpu.append(time.thread_time() - start)
            wall.append(time.perf_counter() - start_wall)
            hidden, last = out.hidden, out.actions
            requests.append(out.comm_mask.sum().item() / len(positions))
    per_agent = 1e3 / len(positions)
    # The first two steps are warm-up.
    return (statistics.median(cpu[2:]) * per_agent, statistics.median(wall[2:]) * per_agent,
            float(np.mean(requests[2:])))


def time_per_robot(net, obs, positions, repeats: int) -> tuple[float, float]:
    """Median over steps of (total robot compute time / N), CPU and wall; messages are passed
    in memory (no transport cost)."""
    n = len(positions)
    fleet = LinkedExchanges(net, [[j] for j in range(n)])
    last = np.full(n, -1)
    cpu, wall = [], []
    for i in range(repeats + 1):
        start, start_wall = time.process_time(), time.perf_counter()
        decision = fleet.tick(0, i, positions, last, obs=obs)
        cpu.append(time.process_time() - start)
        wall.append(time.perf_counter() - start_wall)
        last = decision.rankings[:, 0]
    return statistics.median(cpu[1:]) * 1e3 / n, statistics.median(wall[1:]) * 1e3 / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[16, 64, 128])
    parser.add_argument("--per-robot-agents", type=int, default=16)
    parser.add_argument("--side", type=int, default=0,
                        help="map side; 0 = the test protocol's (40 up to 64 agents, else 80)")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--algos", nargs="+", default=["dhc", "dcc"])
    parser.add_argument("--presets", nargs="+", default=["paper", "small"])
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), random weights "
          f"scaled so DCC communicates (synthetic.make_sensitive)")
    print(f"{'algo':5} {'preset':6} {'mode':10} {'agents':>6} {'map':>4} {'fov nbrs':>8} "
          f"{'cpu ms/agent-step':>18} {'wall ms':>8} {'requests/agent':>15}")
    for algo in args.algos:
        for preset in args.presets:
            net = make_sensitive(build_model(ModelConfig.preset(algo, preset)), 0).eval()
            runs = [("batched", n) for n in args.agents] + [("per-robot", args.per_robot_agents)]
            for mode, n in runs:
                side = args.side or (40 if n <= 64 else 80)
                obs, positions = fleet(n, n, side)
                neighbours = float((obs[:, 0] > 0).sum()) / n
                if mode == "batched":
                    ms, wall, req = time_batched(net, obs, positions, args.repeats)
                    req_text = f"{req:15.2f}" if algo == "dcc" else f"{'-':>15}"
                else:
                    ms, wall = time_per_robot(net, obs, positions, max(3, args.repeats // 3))
                    req_text = f"{'-':>15}"
                print(f"{algo:5} {preset:6} {mode:10} {n:6d} {side:4d} {neighbours:8.2f} "
                      f"{ms:18.3f} {wall:8.3f} {req_text}", flush=True)


if __name__ == "__main__":
    main()
