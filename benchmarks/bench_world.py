"""The simulator's world side at fleet scale, without ROS: what a tick costs the simulator node
besides the policies, and whether that cost grows over a run.

One process drives the code the simulator node runs each tick (`ros/simulator_node.py`,
`ros/fleet_io.run_lockstep`) on a generated lifelong instance (DHC protocol maps, density 0.3,
as `mapf-fleet up --task-source lifelong` makes them), with the robots' moves made up here (not
timed): each robot ranks its moves by distance to its goal, a random ranking with probability
`--noise`, and requests 0-2 peers (DCC's `requested`, as the record keeps it). Per tick, timed
apart:

    take moves   `FleetTicker.on_move` for each robot's RobotMove (rosidl message, built untimed)
                 and `FleetTicker.collect` (the tick's `Decisions`)
    arbitrate    `FleetRun.resolve` (the conflict rule; the fleet's default)
    record       `RunRecorder.add_tick` and `end_tick` (the per-tick journal line, to a file)
    tasks        arrivals, next lifelong goals, requests, idle robots and the arbiter's goals
                 (`FleetRun._arrivals`, `_apply_requests`, `_assign_queued`, `_sync_goals`)
    checkpoint   `RunRecorder.checkpoint` (the record of the run so far, for a process that
                 dies): once at the first tick, as the node does (`fleet_io.run_lockstep`: the
                 journal has every tick after it), or every `--checkpoint-every` ticks (the
                 node before, every 5 s: at a 512-robot fleet's 1 tick/s, every 5 ticks)
    messages     the messages the node publishes each tick: FleetState, every robot's pose and
                 waypoint (PoseStamped), changed goals, goal events, FleetProgress; built and
                 serialised (`rclpy.serialization`, what a publish does first) without a ROS
                 context (`--no-messages`: skipped)
    gc           the garbage collector's own time within the tick (`gc.callbacks`)

With `--ros` (rclpy in this process, its ROS_DOMAIN_ID): the moves come through DDS, published
by a second node of the process before the tick's clock starts, and "take moves" is the wait
until the simulator's subscription (`fleet_io.FleetChannels`, spun in its own thread as the
node does) has them all; "messages" publishes for real through the simulator's publishers.

Printed: ms per tick (mean over the first and the last `--window` ticks) in all and per part,
the checkpoint's cost per call (first and last), the final write, the record's size, the
process's peak memory.

    .venv/bin/python benchmarks/bench_world.py [--robots 512] [--size 80] [--ticks 500]
        [--window 50] [--checkpoint-every N] [--no-messages | --ros] [--json OUT]
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mapf_fleet.fleet.arbiter import DEFAULT_CONFLICT_RULE  # noqa: E402
from mapf_fleet.fleet.lockstep import FleetTicker  # noqa: E402
from mapf_fleet.fleet.run import FleetRun  # noqa: E402
from mapf_fleet.fleet.tasks import LifelongTasks  # noqa: E402
from mapf_fleet.grid.actions import ACTION_DELTAS  # noqa: E402
from mapf_fleet.grid.heuristic import bfs_distances  # noqa: E402
from mapf_fleet.grid.instance import generate_instance  # noqa: E402

# the simulator node's own per-tick record entries (simulator_node.SimulatorNode)
SIM_SERIES = ("collided", "requested", "messages", "executed", "overridden")
PARTS = ("take moves", "arbitrate", "record", "tasks", "checkpoint", "messages", "gc")


class Clock:
    """Seconds per part within the current tick."""

    def __init__(self):
        self.tick: dict[str, float] = {}

    def add(self, part: str, seconds: float) -> None:
        self.tick[part] = self.tick.get(part, 0.0) + seconds

    def wrap(self, obj, name: str, part: str) -> None:
        inner = getattr(obj, name)

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                self.add(part, time.perf_counter() - t0)

        setattr(obj, name, timed)


class Moves:
    """Made-up robot decisions (untimed): the distance ranking, or a random one."""

    def __init__(self, grid, noise: float, seed: int):
        self.grid = np.asarray(grid) != 0
        self.noise = noise
        self.rng = np.random.default_rng(seed)
        self.maps: dict[tuple, np.ndarray] = {}
        self.deltas = np.asarray(ACTION_DELTAS, dtype=np.int64)  # (5, 2), 0 = stay

    def distances(self, goal) -> np.ndarray:
        key = (int(goal[0]), int(goal[1]))
        found = self.maps.get(key)
        if found is None:
            d = bfs_distances(self.grid, key).astype(np.float64)
            d[d < 0] = 1e9
            found = self.maps[key] = np.pad(d, 1, constant_values=1e9)  # off the map: far
        return found

    def rankings(self, positions, goals) -> np.ndarray:
        n = len(positions)
        out = np.empty((n, 5), dtype=np.int64)
        nxt = positions[:, None, :] + self.deltas[None, :, :] + 1  # padded coordinates
        for i in range(n):
            d = self.distances(goals[i])[nxt[i, :, 0], nxt[i, :, 1]]
            out[i] = np.argsort(d + self.rng.random(5) * 0.1, kind="stable")
        noisy = self.rng.random(n) < self.noise
        out[noisy] = np.argsort(self.rng.random((int(noisy.sum()), 5)), axis=1)
        return out

    def messages(self, episode: int, tick: int, rankings: np.ndarray) -> list:
        from mapf_fleet_interfaces.msg import RobotMove

        n = len(rankings)
        out = []
        for i in range(n):
            peers = self.rng.integers(0, n, size=int(self.rng.integers(0, 3))).tolist()
            out.append(RobotMove(episode=episode, tick=tick, robot_id=i,
                                 action=int(rankings[i, 0]),
                                 preferences=[int(a) for a in rankings[i]],
                                 requested=peers, messages_received=2 * len(peers)))
        return out


class Publisher:
    """What the simulator node builds and publishes per tick (simulator_node._publish_state,
    _step; fleet_io.FleetChannels; goals.GoalServer.publish), serialised instead of published."""

    def __init__(self, episode: int, goals):
        from mapf_fleet.ros.common import MapGeometry

        self.episode = episode
        self.geometry = MapGeometry(1.0)
        self.goals_sent = np.array(goals, dtype=np.int64)
        self.bytes = 0

    def tick(self, run, events, done: bool = False) -> None:
        from builtin_interfaces.msg import Time
        from mapf_fleet_interfaces.msg import FleetProgress
        from rclpy.serialization import serialize_message

        from mapf_fleet.ros import common
        from mapf_fleet.ros.fleet_io import fleet_state_msg
        from mapf_fleet.ros.goals import goal_event_msg

        now = time.time()
        stamp = Time(sec=int(now), nanosec=int((now % 1) * 1e9))
        out = []
        # _step: waypoints, changed goals; GoalServer.publish: the tick's goal events
        out += [common.cell_pose(int(r), int(c), self.geometry, stamp)
                for r, c in run.positions.tolist()]
        goals = run.goals
        changed = np.flatnonzero((goals != self.goals_sent).any(axis=1)).tolist()
        out += [common.cell_pose(*goals[i], self.geometry) for i in changed]
        self.goals_sent = goals.copy()
        out += [goal_event_msg(self.episode, e) for e in events]
        out.append(FleetProgress(**run.progress([])))
        # _publish_state: the state, then every robot's pose
        positions = run.positions
        out.append(fleet_state_msg(self.episode, run.tick, positions, goals, run.last_actions,
                                   done, stamp))
        out += [common.cell_pose(*positions[i], self.geometry, stamp)
                for i in range(len(positions))]
        for msg in out:
            self.bytes += len(serialize_message(msg))


class RosPublisher:
    """`--ros`: the simulator's own publishers (`fleet_io.FleetChannels`, the robots' pose
    publishers) on a node of this process, publishing for real (nobody subscribes but the
    process's own mover node), and the moves taken through the channels' subscription."""

    def __init__(self, episode: int, goals, ticker, num_robots: int):
        import rclpy
        from geometry_msgs.msg import PoseStamped
        from mapf_fleet_interfaces.msg import RobotMove
        from rclpy.executors import SingleThreadedExecutor

        from mapf_fleet.ros import common, fleet_io

        common.prepare_environment()
        rclpy.init()
        self.node = rclpy.create_node("mapf_simulator")
        self.geometry = common.MapGeometry(1.0)
        self.ticker = ticker
        self.channels = fleet_io.FleetChannels(self.node, ticker, self.geometry)
        quiet = common.quiet_publisher_events()
        self.pose_pubs = [self.node.create_publisher(
            PoseStamped, common.rel(common.pose_topic(i)), common.reliable_qos(10),
            event_callbacks=quiet) for i in range(num_robots)]
        self.channels._goals_sent = np.array(goals, dtype=np.int64)
        self.mover = rclpy.create_node("bench_world_mover")
        self.moves_pub = self.mover.create_publisher(RobotMove, common.rel(common.MOVES_TOPIC),
                                                     common.reliable_qos(1000))
        executor = SingleThreadedExecutor()
        executor.add_node(self.node)
        self.spinner = common.SpinThread(executor).start()
        deadline = time.monotonic() + 30
        while self.moves_pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            time.sleep(0.1)

    def send_moves(self, msgs) -> None:
        for msg in msgs:
            self.moves_pub.publish(msg)

    def tick(self, run, events, done: bool = False) -> None:
        from mapf_fleet_interfaces.msg import FleetProgress

        from mapf_fleet.ros import common

        self.channels.publish_waypoints(run.positions)
        self.channels.publish_goal_changes(run.goals, events)
        self.channels.progress_pub.publish(FleetProgress(**run.progress([])))
        stamp = self.channels.publish_state(run.positions, run.goals, run.last_actions, done)
        for i, pub in enumerate(self.pose_pubs):
            pub.publish(common.cell_pose(*run.positions[i], self.geometry, stamp))

    def close(self) -> None:
        import rclpy

        self.spinner.stop()
        self.mover.destroy_node()
        self.node.destroy_node()
        rclpy.try_shutdown()


def run(args) -> dict:
    inst = generate_instance(args.size, args.robots, args.density, args.seed)
    tasks = LifelongTasks(grid=inst.grid, seed=args.seed)
    episode = 12345
    fleet = FleetRun(inst.grid, inst.starts, tasks, inst.goals, rule=args.rule,
                     max_steps=args.ticks, episode=episode, series=SIM_SERIES)
    ticker = FleetTicker(args.robots, episode)
    moves = Moves(inst.grid, args.noise, args.seed)
    ros = RosPublisher(episode, fleet.goals, ticker, args.robots) if args.ros else None
    publisher = ros or (None if args.no_messages else Publisher(episode, fleet.goals))
    if publisher is not None and ros is None:  # the imports, before the first tick
        Publisher(episode, fleet.goals).tick(fleet, [])
    clock = Clock()
    clock.wrap(fleet, "resolve", "arbitrate")
    clock.wrap(fleet.recorder, "add_tick", "record")
    clock.wrap(fleet.recorder, "end_tick", "record")
    for name in ("_arrivals", "_apply_requests", "_assign_queued", "_sync_goals"):
        clock.wrap(fleet, name, "tasks")
    gc_started = [0.0]

    def on_gc(phase, info):
        if phase == "start":
            gc_started[0] = time.perf_counter()
        else:
            clock.add("gc", time.perf_counter() - gc_started[0])

    gc.callbacks.append(on_gc)
    work = tempfile.mkdtemp(prefix="bench_world_")
    record_file = os.path.join(work, "run.json")
    fleet.recorder.open_journal(record_file)
    ticks, checkpoints = [], []
    try:
        while not fleet.finished():
            rankings = moves.rankings(fleet.positions, fleet.goals)  # the policies: untimed
            msgs = moves.messages(episode, ticker.tick, rankings)
            clock.tick = {}
            if ros is not None:  # through DDS: the wait for the last move is timed
                ros.send_moves(msgs)
            started = time.perf_counter()
            t0 = time.perf_counter()
            if ros is None:
                for msg in msgs:
                    ticker.on_move(msg)
            decisions = ticker.collect(10.0 if ros is not None else 0.0)
            clock.add("take moves", time.perf_counter() - t0)
            result, events = fleet.step(decisions, requested=decisions.requested,
                                        messages=decisions.messages)
            ticker.advance()
            fleet.progress(decisions.missing)
            if fleet.steps % args.progress_every == 0:
                fleet.progress_text()
            if (fleet.steps % args.checkpoint_every == 0 if args.checkpoint_every
                    else fleet.steps == 1):
                t0 = time.perf_counter()
                fleet.recorder.checkpoint(record_file, fleet.tick)
                seconds = time.perf_counter() - t0
                clock.add("checkpoint", seconds)
                checkpoints.append((fleet.steps, seconds))
            if publisher is not None:
                t0 = time.perf_counter()
                publisher.tick(fleet, events)
                clock.add("messages", time.perf_counter() - t0)
            total = time.perf_counter() - started
            ticks.append({"total": total, **clock.tick})
        fleet.finish()
        t0 = time.perf_counter()
        fleet.recorder.write(record_file)
        final_write = time.perf_counter() - t0
        fleet.recorder.close_journal(record_file)
        record_bytes = os.path.getsize(record_file)
        os.remove(record_file)
        os.rmdir(work)
    finally:
        gc.callbacks.remove(on_gc)
        if ros is not None:
            ros.close()

    def window(rows):
        keys = ("total",) + PARTS
        return {k: 1000 * float(np.mean([r.get(k, 0.0) for r in rows])) for k in keys}

    w = min(args.window, len(ticks) // 2)
    return {"robots": args.robots, "size": args.size, "ticks": len(ticks), "rule": args.rule,
            "goals_reached": fleet.goals_reached,
            "first_ms": window(ticks[:w]), "last_ms": window(ticks[-w:]), "window": w,
            "checkpoint_first_ms": 1000 * checkpoints[0][1] if checkpoints else None,
            "checkpoint_last_ms": 1000 * checkpoints[-1][1] if checkpoints else None,
            "final_write_ms": 1000 * final_write, "record_mb": record_bytes / 1e6,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "missed": fleet.recorder.missed,
            "message_mb_per_tick": (publisher.bytes / len(ticks) / 1e6)
            if publisher is not None and ros is None else None}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=512)
    ap.add_argument("--size", type=int, default=80)
    ap.add_argument("--density", type=float, default=0.3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ticks", type=int, default=500)
    ap.add_argument("--window", type=int, default=50)
    ap.add_argument("--rule", default=DEFAULT_CONFLICT_RULE)
    ap.add_argument("--noise", type=float, default=0.1,
                    help="probability of a random ranking per robot and tick")
    ap.add_argument("--checkpoint-every", type=int, default=0,
                    help="ticks between record checkpoints (0: once at the first tick, as "
                         "the node)")
    ap.add_argument("--progress-every", type=int, default=10)
    ap.add_argument("--no-messages", action="store_true")
    ap.add_argument("--ros", action="store_true",
                    help="publish for real on a node of this process (rclpy, ROS_DOMAIN_ID of "
                         "the environment) and take the moves through DDS")
    ap.add_argument("--json", default="")
    args = ap.parse_args(argv)
    out = run(args)
    print(f"{out['robots']} robots, {out['size']}x{out['size']}, {out['ticks']} ticks, "
          f"{out['rule']}, {out['goals_reached']} goals reached, {out['missed']} missed"
          + (" (ROS: published, moves through DDS)" if args.ros else ""))
    header = f"{'ms per tick':<18}" + "".join(f"{k:>12}" for k in ("total",) + PARTS)
    print(header)
    for name in ("first", "last"):
        row = out[f"{name}_ms"]
        print(f"{name + ' ' + str(out['window']) + ' ticks':<18}"
              + "".join(f"{row[k]:>12.1f}" for k in ("total",) + PARTS))
    if out["checkpoint_first_ms"] is not None:
        print(f"checkpoint per call: first {out['checkpoint_first_ms']:.1f} ms, last "
              f"{out['checkpoint_last_ms']:.1f} ms ("
              + (f"every {args.checkpoint_every} ticks)" if args.checkpoint_every
                 else "once, at the first tick)"))
    print(f"final record write {out['final_write_ms']:.0f} ms, record {out['record_mb']:.1f} MB, "
          f"peak RSS {out['peak_rss_mb']:.0f} MB"
          + (f", messages {out['message_mb_per_tick']:.2f} MB per tick"
             if out["message_mb_per_tick"] is not None else ""))
    if args.json:
        Path(args.json).write_text(json.dumps({"args": vars(args), **out}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
