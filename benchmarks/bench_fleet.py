"""Fleet throughput and where a tick goes: `mapf-fleet up` at 32 / 64 / 128 / 256 / 512 / 1,024 robots in
the recommended layouts (32: 24x24, 4 processes x 8 robots; 64: 32x32, 4 x 16; 128: 40x40, 4 x 32;
256: 56x56, 8 x 32; 512: 80x80, 8 x 64; 1,024: 112x112, 8 x 128), DHC and DCC, beside the batched evaluator (MAPFEnv + network.step, one
thread) on the same instance and checkpoint.

Per run: ticks/s from the first progress line to the last (the simulator logs one every 5 ticks
here, `progress_every`;
start-up excluded), the time per tick over the first and the last quarter of the run (flat or
growing), missed decisions, and the split of a tick from the hubs' own timing
(`models.exchange.TickTiming`, logged by every policy process, kept with --log-dir), averaged
over the hubs, in ms per tick:
  latency  fleet state stamped by the simulator -> the hub's callback (publish + DDS),
  wake     callback -> the hub's decision thread,
  observe  FOV observations, network (torch), send (peer messages, DCC batch calls),
  wait     for the other processes' messages, moves (ranking, publishing the moves),
  sim+rest the tick minus what the hubs account for: the simulator taking the moves,
           arbitrating (PIBT), publishing waypoints / poses / markers / the next state.
DCC message counts: requests + replies to other processes per tick, and the service calls that
carried them (one DccBatch per pair of processes and phase).

Each run also prints its ready time (launch to the first tick) and the peak memory of its
processes (RSS summed over `up` and its descendants, sampled every 2 s), and the largest sample
over the first and over the last fifth of the ticks (bounded or growing); a run stopped by
--run-timeout prints the tail of its output instead of figures.

    python benchmarks/bench_fleet.py [--robots 32 64 128 256 512] [--algos dcc dhc] [--steps 60]
        [--task-source lifelong]   (a continuous run: a new goal on arrival, every tick played)
        [--window 50]              (ms per tick over the first and the last 50 ticks)
        [--run-timeout 600]
        [--conflict-rule lacam --planning-budget 0.2]
        [--default-layout]         (no --nodes-per-process: the layout `up` chooses)
        [--tick-period 0.75]       (a fixed control rate: the simulator's tick_period)
        [--batched-steps 20]       (steps of the batched evaluator timed beside each run)

On the 2-core development machine one core was busy with a training job: figures are as measured.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
CHECKPOINTS = {"dcc": REPO / "models" / "default.pt",
               "dhc": REPO / "models" / "dhc_5x30_cl_alpha1.0.pt"}
# robots -> (map side, robots per process)
# 512: 8 processes x 64, the layout measured to become ready (16 x 32 never did: discovery and
# start-up of 17 processes on a loaded 2-core machine)
# 1,024: 112x112 (the same robots per free cell), 8 x 128, the layout `up` recommends
LAYOUTS = {32: (24, 8), 64: (32, 16), 128: (40, 32), 256: (56, 32), 512: (80, 64),
           1024: (112, 128)}
PHASES = ("latency", "wake", "observe", "network", "send", "wait", "moves")
# the simulator's progress lines only (they end with the missed decisions), not its warnings
TICK_LINE = re.compile(r"\[(\d+\.\d+)\] \[[^\]]*mapf_simulator\]: tick (\d+): .*missed "
                       r"decisions?$", re.M)
# the simulator's line when it starts ticking (every robot ready, or the start-up timeout)
READY_LINE = re.compile(r"\[(\d+\.\d+)\] \[[^\]]*mapf_simulator\]: (?:all \d+ robots ready|"
                        r"starting without ready robots)")
# `up`'s line naming the layout it chose (no --nodes-per-process given)
LAYOUT_LINE = re.compile(r"(\d+) robots in (\d+) policy process\(es\) of up to (\d+) robots")
HUB_LINE = re.compile(r"hub timing over (\d+) ticks, ms per tick: (.*?); last")
SENT = re.compile(r"to other processes (\d+) in (\d+) batch calls")


def batched_ms_per_step(checkpoint, instance, steps):
    """ms per step of the evaluator's own rollout (MAPFEnv + LearnedPolicy, one thread)."""
    import torch

    from mapf_fleet.grid.env import EnvConfig, MAPFEnv
    from mapf_fleet.models.checkpoint import load_checkpoint
    from mapf_fleet.models.policy import LearnedPolicy

    torch.set_num_threads(1)
    model, _ = load_checkpoint(str(checkpoint))
    policy = LearnedPolicy(model, device="cpu")
    env = MAPFEnv(instance, EnvConfig(observation=policy.observation))
    obs, done, count = env.reset(), False, 0
    policy.reset(1, env.num_agents)
    start = time.perf_counter()
    while count < steps and not done:
        actions = policy.act(obs[None], env.positions[None])
        obs, _, done, _ = env.step(actions[0])
        count += 1
    return 1000 * (time.perf_counter() - start) / max(1, count)


def tick_times(output: str) -> tuple[list[float], float]:
    """Seconds per tick between the simulator's progress lines, and the ticks per second from
    the first line to the last."""
    stamps = [(int(m[2]), float(m[1])) for m in TICK_LINE.finditer(output)]
    times = [(b[1] - a[1]) / (b[0] - a[0]) for a, b in zip(stamps, stamps[1:]) if b[0] > a[0]]
    span = stamps[-1][1] - stamps[0][1] if len(stamps) > 1 else 0.0
    return times, ((stamps[-1][0] - stamps[0][0]) / span if span > 0 else 0.0)


def hub_split(log_dir: str) -> tuple[dict, float, float]:
    """Mean ms per tick of each phase over the hubs (their last timing line), and the DCC
    messages / batch calls to other processes per tick (summed over the hubs)."""
    phases, messages, calls = [], 0.0, 0.0
    for log in sorted(Path(log_dir).glob("*.log")):
        lines = [m for m in HUB_LINE.finditer(log.read_text())]
        if not lines:
            continue
        last = lines[-1]
        ticks = int(last[1])
        phases.append({p: float(v) for p, v in
                       (part.split() for part in last[2].split(", "))})
        sent = SENT.findall(log.read_text())
        if sent and ticks:
            messages += int(sent[-1][0]) / ticks
            calls += int(sent[-1][1]) / ticks
    mean = {p: sum(h.get(p, 0.0) for h in phases) / max(1, len(phases)) for p in PHASES}
    return mean, messages, calls


def run_fleet(checkpoint, robots, size, per_process, seed, steps, domain,
              task_source="instance", conflict_rule=None, planning_budget=None, timeout=1800,
              tick_period=0.0, guidance=None):
    """One `up` run: (its record or None when it wrote none, (tick times, ticks/s), the hubs'
    split, seconds from the launch to the first tick or None, peak memory of its processes in
    MB (their RSS summed, sampled every 2 s), the output's tail)."""
    work = tempfile.mkdtemp(prefix="bench_fleet_")
    record, logs = os.path.join(work, "run.json"), os.path.join(work, "logs")
    cmd = [sys.executable, "-m", "mapf_fleet.cli", "up", "--checkpoint", str(checkpoint),
           "--num-robots", str(robots), "--size", str(size), "--seed", str(seed),
           "--max-steps", str(steps), "--record", record, "--domain-id", str(domain),
           "--log-dir", logs, "--task-source", task_source]
    if per_process:  # else the layout `up` chooses (ros/layout_choice.py), as a user types it
        cmd += ["--nodes-per-process", str(per_process)]
    if conflict_rule:
        cmd += ["--conflict-rule", conflict_rule]
    if planning_budget is not None:
        cmd += ["--planning-budget", str(planning_budget)]
    if guidance:  # else `up`'s default (the checkpoint's recorded guidance, else the fleet's)
        cmd += ["--guidance", guidance]
    cmd += ["--ros-args", "-p", "progress_every:=5"]
    if tick_period:  # a fixed control rate: a tick starts every tick_period s at the earliest
        cmd += ["-p", f"tick_period:={tick_period}"]
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    launched = time.time()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    peak, stop, series = [0], threading.Event(), []  # series: (seconds since launch, MB)

    def sample():  # up's children run in their own sessions: walk the process tree
        while not stop.wait(2.0):
            out = subprocess.run(["ps", "-e", "-o", "pid=,ppid=,rss="], capture_output=True,
                                 text=True).stdout
            rows = [tuple(map(int, line.split())) for line in out.splitlines() if line.strip()]
            tree, total = {proc.pid}, 0
            for _ in range(4):  # up -> launcher/ros2 -> nodes: a few generations
                tree |= {pid for pid, parent, _ in rows if parent in tree}
            total = sum(rss for pid, _, rss in rows if pid in tree)
            peak[0] = max(peak[0], total // 1024)
            series.append((time.time() - launched, total // 1024))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGINT)  # up stops its fleet on SIGINT
        try:
            stdout, stderr = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            stdout, stderr = proc.communicate()
    stop.set()
    # the whole output beside the record and the logs (the printed tail is its last lines)
    Path(work, "output.log").write_text(stdout + stderr)
    try:
        run = json.loads(Path(record).read_text())
    except (OSError, ValueError):
        run = None
    stamps = [float(m[1]) for m in TICK_LINE.finditer(stdout)]
    # ready: launch to the simulator's "all robots ready" (else to its first progress line)
    started = READY_LINE.search(stdout + stderr)
    ready = (float(started[1]) if started else stamps[0] if stamps else launched - 1) - launched
    ready = ready if ready >= 0 else None
    # memory once the fleet runs: over the first and the last fifth of the ticks (bounded or
    # growing with the run)
    running = [mb for at, mb in series if stamps and stamps[0] - launched <= at
               <= stamps[-1] - launched]
    fifth = max(1, len(running) // 5)
    memory = (peak[0], (max(running[:fifth]) if running else 0,
                        max(running[-fifth:]) if running else 0))
    chosen = LAYOUT_LINE.search(stdout + stderr)
    layout = (int(chosen[2]), int(chosen[3])) if chosen else None  # (processes, robots each)
    return (run, tick_times(stdout), hub_split(logs), ready, memory, (stdout + stderr)[-2000:],
            layout)


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robots", type=int, nargs="+", default=sorted(LAYOUTS),
                        choices=sorted(LAYOUTS))
    parser.add_argument("--algos", nargs="+", default=["dcc", "dhc"], choices=sorted(CHECKPOINTS))
    parser.add_argument("--steps", type=int, default=60, help="ticks per run (default: 60)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--window", type=int, default=0,
                        help="ticks compared at the start and the end of the run (ms per tick "
                             "over the first and the last WINDOW ticks, from the progress lines "
                             "every 5 ticks); default: a quarter of the run each")
    parser.add_argument("--task-source", choices=["instance", "lifelong"], default="instance",
                        help="instance: the one-shot episode (ends when all are on goal); "
                             "lifelong: a continuous run, a new goal on arrival, all --steps "
                             "ticks")
    parser.add_argument("--conflict-rule", default=None,
                        help="the arbiter's conflict rule (default: up's, pibt_anchor)")
    parser.add_argument("--planning-budget", type=float, default=None,
                        help="--conflict-rule lacam: seconds per re-plan (default: up's, 1)")
    parser.add_argument("--batched-steps", type=int, default=0,
                        help="steps of the batched evaluator timed beside each run (default: "
                             "--steps; its ms per step are nearly flat, 1,024 agents take "
                             "minutes)")
    parser.add_argument("--default-layout", action="store_true",
                        help="leave --nodes-per-process out: the layout `up` chooses from the "
                             "robot count and the memory available (as a user types it)")
    parser.add_argument("--domain-id", type=int, default=150,
                        help="first ROS_DOMAIN_ID used (one per run; default: 150)")
    parser.add_argument("--tick-period", type=float, default=0.0,
                        help="the simulator's tick_period: a fixed control rate (0: as fast as "
                             "the robots decide)")
    parser.add_argument("--guidance", help="up --guidance (default: up's own default)")
    parser.add_argument("--run-timeout", type=float, default=1800,
                        help="seconds a run may take before it is stopped (default 1800)")
    args = parser.parse_args()
    from mapf_fleet.grid.instance import generate_instance

    head = (f"{'robots':>6} {'algo':<4} {'layout':<14} {'ticks/s':>7} {'ms/tick':>13} "
            f"{'missed':>6} | " + " ".join(f"{p:>7}" for p in PHASES)
            + f" {'sim+rest':>8} | {'msgs/calls':>10} | {'batched':>7} {'x':>5}")
    print(head)
    print("-" * len(head))
    domain = args.domain_id
    for robots in args.robots:
        size, per_process = LAYOUTS[robots]
        instance = generate_instance(size, robots, 0.3, args.seed)
        for algo in args.algos:
            checkpoint = CHECKPOINTS[algo]
            batched = batched_ms_per_step(checkpoint, instance,
                                          args.batched_steps or args.steps)
            run, ticks, (split, messages, calls), ready, memory, tail, chosen = run_fleet(
                checkpoint, robots, size, None if args.default_layout else per_process,
                args.seed, args.steps, domain, args.task_source, args.conflict_rule,
                args.planning_budget, args.run_timeout, args.tick_period, args.guidance)
            domain += 1
            if args.default_layout:
                processes, per_process = chosen or (1, 1)  # no line: a process per robot
            else:
                processes = -(-robots // per_process)
            layout = f"{processes} x {per_process}, {size}x{size}"
            ready_text = "never" if ready is None else f"{ready:.0f} s"
            memory, (early, late) = memory
            print(f"{robots:>6} {algo:<4} {layout:<14} ready {ready_text}, peak memory "
                  f"{memory} MB ({memory / robots:.1f} MB per robot); running: {early} MB over "
                  f"the first fifth of the ticks, {late} MB over the last", flush=True)
            if run is None:
                print(f"{'':>6} no record within {args.run_timeout} s; output's tail:\n{tail}",
                      flush=True)
                continue
            if run.get("incomplete"):  # the simulator ended before its outcome
                print(f"{'':>6} {run['summary']}; output's tail:\n{tail}", flush=True)
            ticks, rate = ticks
            # ticks holds one mean per 5 ticks (progress_every)
            quarter = max(1, args.window // 5 if args.window else len(ticks) // 4)
            start_ms = 1000 * sum(ticks[:quarter]) / quarter if ticks else 0.0
            end_ms = 1000 * sum(ticks[-quarter:]) / quarter if ticks else 0.0
            per_tick = 1000 / rate if rate else 0.0
            print(f"{robots:>6} {algo:<4} {layout:<14} {len(ticks) * 5} ticks timed: "
                  f"{1000 / start_ms if start_ms else 0:.2f} ticks/s over the first "
                  f"{quarter * 5}, {1000 / end_ms if end_ms else 0:.2f} over the last "
                  f"{quarter * 5}; missed decisions {run['missed_decisions']}", flush=True)
            rest = per_tick - sum(split[p] for p in PHASES)
            comm = f"{messages:.0f}/{calls:.1f}" if algo == "dcc" else "-"
            print(f"{robots:>6} {algo:<4} {layout:<14} {rate:>7.2f} "
                  f"{f'{start_ms:.0f}->{end_ms:.0f}':>13} {run['missed_decisions']:>6} | "
                  + " ".join(f"{split[p]:>7.1f}" for p in PHASES)
                  + f" {rest:>8.1f} | {comm:>10} | {batched:>7.1f} {per_tick / batched:>5.0f}",
                  flush=True)
            planner = run.get("planner")
            if planner:  # the planning arbiter's counters (conflict rule lacam)
                print(f"{'':>6} planner: {planner['planner_calls']} calls, "
                      f"{planner['planner_seconds_per_call'] * 1000:.0f} ms per call (max "
                      f"{planner['planner_max_seconds'] * 1000:.0f}), "
                      f"{planner['planner_seconds'] / max(planner['ticks'], 1) * 1000:.1f} ms per "
                      f"tick, fallback ticks {planner['fallback_ticks']}/{planner['ticks']}",
                      flush=True)


if __name__ == "__main__":
    main()
