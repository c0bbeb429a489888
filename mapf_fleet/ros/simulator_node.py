"""SimulatorNode: the grid world as a ROS node, stepping the fleet in lockstep ticks.

Tick k: publish the fleet state of k (and poses, markers); wait for every robot's move for k (a
move missing after `decision_timeout` counts as "stay" and is reported); apply the grid world's
conflict rules (grid.resolve_moves); publish progress; go on with k + 1. At the end the outcome
(success, steps, collisions, missed decisions) is published (latched) and optionally written to
`record_file` as JSON with the whole trajectory.
"""

from __future__ import annotations

import json
import random
import sys
import threading
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from mapf_fleet_interfaces.msg import (FleetOutcome, FleetProgress, FleetState, RobotMove,
                                       RobotStatus)
from nav_msgs.msg import OccupancyGrid
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from visualization_msgs.msg import Marker, MarkerArray

from mapf_fleet.ros import common
from mapf_fleet.ros.instances import InstanceSource

PARAMETERS = {
    # name: (default, description)
    "instance_file": ("", "instance YAML (grid rows, starts, goals); overrides the rest"),
    "map_file": ("", "MovingAI .map file (with scen_file)"),
    "scen_file": ("", "MovingAI .scen file (with map_file)"),
    "num_robots": (8, "robots to generate or to take from the .scen file"),
    "size": (16, "side of a generated square map"),
    "density": (0.3, "obstacle density of a generated map"),
    "seed": (0, "seed of a generated instance"),
    "max_steps": (256, "tick limit: the run fails when robots are not all on goal by then"),
    "decision_timeout": (5.0, "seconds to wait for a robot's move before it counts as stay"),
    "startup_timeout": (60.0, "seconds to wait for every policy node to report ready"),
    "tick_period": (0.0, "minimum seconds per tick (0: as fast as the robots decide)"),
    "resolution": (1.0, "metres per cell in poses and the map"),
    "record_file": ("", "write the run's trajectory and outcome to this JSON file"),
    "progress_every": (10, "log progress every this many ticks"),
    "start_tick": (0, "first tick number (a restarted simulator may continue a count)"),
}


class SimulatorNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__("mapf_simulator", **node_kwargs)
        for name, (default, text) in PARAMETERS.items():
            self.declare_parameter(name, default, ParameterDescriptor(description=text))
        p = {name: self.get_parameter(name).value for name in PARAMETERS}
        self.params = p
        source = InstanceSource(p["instance_file"], p["map_file"], p["scen_file"],
                                int(p["num_robots"]), int(p["size"]), float(p["density"]),
                                int(p["seed"]))
        self.instance = source.load()
        if float(p["decision_timeout"]) <= 0:
            raise ValueError(f"decision_timeout must be > 0, got {p['decision_timeout']}")
        self.geometry = common.MapGeometry(float(p["resolution"]))
        self.num_robots = self.instance.num_agents
        self.episode = random.getrandbits(63)
        self.positions = np.array(self.instance.starts, dtype=np.int64)
        self.goals = np.array(self.instance.goals, dtype=np.int64)
        # -1: no action yet (MAPFEnv.last_actions; DCC feeds a zero one-hot then)
        self.last_actions = np.full(self.num_robots, -1, dtype=np.int64)
        self.tick = int(p["start_tick"])
        self.collisions = 0
        self.missed = 0
        self.missed_robots: set[int] = set()
        self.record = {"episode": self.episode, "positions": [self.positions.tolist()],
                       "actions": [], "collided": [], "missed": [],
                       "requested": [], "messages": []}
        self.outcome: FleetOutcome | None = None
        self.finished = threading.Event()

        self._moves_lock = threading.Condition()
        self._moves: dict[int, int] = {}
        self._comm: dict[int, tuple[list[int], int]] = {}  # robot -> (requested, received)
        self._ready: dict[int, RobotStatus] = {}

        self.map_pub = self.create_publisher(OccupancyGrid, common.MAP_TOPIC, common.latched_qos())
        self.state_pub = self.create_publisher(FleetState, common.STATE_TOPIC,
                                               common.reliable_qos(10))
        self.progress_pub = self.create_publisher(FleetProgress, common.PROGRESS_TOPIC,
                                                  common.reliable_qos(10))
        self.outcome_pub = self.create_publisher(FleetOutcome, common.OUTCOME_TOPIC,
                                                 common.latched_qos())
        self.markers_pub = self.create_publisher(MarkerArray, common.MARKERS_TOPIC,
                                                 common.reliable_qos(2))
        quiet = common.quiet_publisher_events()  # per-robot publishers: keep the wait set small
        self.pose_pubs = [self.create_publisher(PoseStamped, common.pose_topic(i),
                                                common.reliable_qos(10), event_callbacks=quiet)
                          for i in range(self.num_robots)]
        self.goal_pubs = [self.create_publisher(PoseStamped, common.goal_topic(i),
                                                common.latched_qos(), event_callbacks=quiet)
                          for i in range(self.num_robots)]
        self.create_subscription(RobotMove, common.MOVES_TOPIC, self._on_move,
                                 common.reliable_qos(1000))
        self.create_subscription(RobotStatus, common.STATUS_TOPIC, self._on_status,
                                 common.reliable_qos(1000))
        self.map_pub.publish(common.grid_to_occupancy(self.instance.grid, self.geometry))
        for i, pub in enumerate(self.goal_pubs):
            pub.publish(common.cell_pose(*self.goals[i], self.geometry))
        self.get_logger().info(
            f"instance {self.instance.size[0]}x{self.instance.size[1]} with {self.num_robots} "
            f"robots, episode {self.episode}")
        self._thread = threading.Thread(target=self._run_safely, name="simulator", daemon=True)

    # ---- callbacks (executor threads): store and notify only ----
    def _on_move(self, msg: RobotMove):
        with self._moves_lock:
            if msg.episode != self.episode or msg.tick != self.tick:
                return  # stale tick or another run
            if msg.robot_id >= self.num_robots or msg.action > 4:
                self.get_logger().warning(f"ignored bad move {msg.robot_id}/{msg.action}")
                return
            self._moves[int(msg.robot_id)] = int(msg.action)
            self._comm[int(msg.robot_id)] = ([int(j) for j in msg.requested],
                                             int(msg.messages_received))
            if msg.missing_peers:
                self.get_logger().warning(
                    f"tick {msg.tick}: robot {msg.robot_id} decided without peers "
                    f"{list(msg.missing_peers)} (timed out)")
            self._moves_lock.notify_all()

    def _on_status(self, msg: RobotStatus):
        with self._moves_lock:
            if msg.robot_id < self.num_robots and msg.ready:
                self._ready[int(msg.robot_id)] = msg
                self._moves_lock.notify_all()

    # ---- the lockstep loop (own thread) ----
    def start(self):
        self._thread.start()

    def _run_safely(self):
        try:
            self._run()
        except Exception as exc:  # keep the process alive long enough to report
            self.get_logger().error(f"simulator failed: {exc!r}")
            self.outcome = FleetOutcome(episode=self.episode, success=False,
                                        summary=f"simulator failed: {exc!r}")
        finally:
            self.finished.set()

    def _wait_ready(self):
        deadline = time.monotonic() + float(self.params["startup_timeout"])
        need = self.num_robots
        with self._moves_lock:
            while time.monotonic() < deadline:
                ready = [s for s in self._ready.values() if s.peers >= need]
                if len(ready) >= need:
                    break
                self._moves_lock.wait(0.1)
            missing = sorted(set(range(need)) - {s.robot_id for s in self._ready.values()
                                                 if s.peers >= need})
        if missing:
            self.get_logger().warning(f"starting without ready robots {missing} "
                                      f"after {self.params['startup_timeout']} s")
        else:
            self.get_logger().info(f"all {need} robots ready")

    def _run(self):
        from mapf_fleet.grid.env import resolve_moves

        self._wait_ready()
        max_steps = int(self.params["max_steps"])
        timeout = float(self.params["decision_timeout"])
        period = float(self.params["tick_period"])
        steps = 0
        run_started = time.monotonic()
        success = bool((self.positions == self.goals).all())
        while not success and steps < max_steps and rclpy.ok():
            started = time.monotonic()
            self._publish_state(done=False)
            deadline = started + timeout
            with self._moves_lock:
                while len(self._moves) < self.num_robots:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        break
                    self._moves_lock.wait(remaining)
                moves = dict(self._moves)
                comm = dict(self._comm)
                self._moves, self._comm = {}, {}
                self.tick += 1
            missing = sorted(set(range(self.num_robots)) - set(moves))
            actions = np.array([moves.get(i, 0) for i in range(self.num_robots)], dtype=np.int64)
            if missing:
                self.missed += len(missing)
                self.missed_robots.update(missing)
                self.get_logger().warning(f"tick {self.tick - 1}: no decision from robots "
                                          f"{missing} within {timeout} s: they stay")
            new_positions, collided = resolve_moves(self.instance.grid, self.positions, actions)
            self.positions = np.asarray(new_positions, dtype=np.int64)
            self.last_actions = actions
            collided = np.asarray(collided, dtype=bool)
            self.collisions += int(collided.sum())
            steps += 1
            success = bool((self.positions == self.goals).all())
            self.record["actions"].append(actions.tolist())
            self.record["collided"].append(np.flatnonzero(collided).tolist())
            self.record["missed"].append(missing)
            # who talked to whom: per robot its partners (DHC) / requested peers (DCC), and the
            # peer messages it used
            self.record["requested"].append([comm.get(i, ([], 0))[0]
                                             for i in range(self.num_robots)])
            self.record["messages"].append([comm.get(i, ([], 0))[1]
                                            for i in range(self.num_robots)])
            self.record["positions"].append(self.positions.tolist())
            self.progress_pub.publish(FleetProgress(
                episode=self.episode, tick=self.tick, max_steps=max_steps,
                num_robots=self.num_robots,
                on_goal=int((self.positions == self.goals).all(1).sum()),
                collisions=self.collisions, missed_decisions=self.missed, missed_robots=missing))
            if steps % int(self.params["progress_every"]) == 0:
                self.get_logger().info(
                    f"tick {self.tick}: {int((self.positions == self.goals).all(1).sum())}/"
                    f"{self.num_robots} on goal, {self.collisions} collisions, "
                    f"{self.missed} missed decisions")
            if period > 0:
                time.sleep(max(0.0, period - (time.monotonic() - started)))
        self._publish_state(done=True)
        on_goal = int((self.positions == self.goals).all(1).sum())
        summary = (f"{'success' if success else 'failure'}: {on_goal}/{self.num_robots} robots on "
                   f"goal after {steps} steps, {self.collisions} collisions, {self.missed} missed "
                   f"decisions" + (f" (robots {sorted(self.missed_robots)})"
                                   if self.missed_robots else ""))
        self.outcome = FleetOutcome(
            episode=self.episode, success=success, steps=steps, num_robots=self.num_robots,
            collisions=self.collisions, missed_decisions=self.missed,
            missed_robots=sorted(self.missed_robots), summary=summary)
        self.outcome_pub.publish(self.outcome)
        self.get_logger().info(summary)
        if self.params["record_file"]:
            self.record.update(run_seconds=time.monotonic() - run_started,
                               success=success, steps=steps, collisions=self.collisions,
                               missed_decisions=self.missed, summary=summary)
            with open(self.params["record_file"], "w") as handle:
                json.dump(self.record, handle)

    def _publish_state(self, done: bool):
        stamp = self.get_clock().now().to_msg()
        msg = FleetState(episode=self.episode, tick=self.tick, done=done,
                         rows=self.positions[:, 0].tolist(), cols=self.positions[:, 1].tolist(),
                         goal_rows=self.goals[:, 0].tolist(), goal_cols=self.goals[:, 1].tolist(),
                         last_actions=self.last_actions.tolist())
        msg.header.stamp = stamp
        msg.header.frame_id = common.FRAME_ID
        self.state_pub.publish(msg)
        for i, pub in enumerate(self.pose_pubs):
            pub.publish(common.cell_pose(*self.positions[i], self.geometry, stamp))
        self.markers_pub.publish(self._markers(stamp))

    def _markers(self, stamp) -> MarkerArray:
        return fleet_markers(self.positions, self.goals, self.geometry, stamp)


def fleet_markers(positions, goals, geometry, stamp) -> MarkerArray:
    """Robots (cylinders) and goals (cubes), one colour per robot, for viewers."""
    array = MarkerArray()
    for i in range(len(positions)):
        for kind, cell, shape in (("robot", positions[i], Marker.CYLINDER),
                                  ("goal", goals[i], Marker.CUBE)):
            marker = Marker()
            marker.header.frame_id = common.FRAME_ID
            marker.header.stamp = stamp
            marker.ns = kind
            marker.id = i
            marker.type = shape
            marker.action = Marker.ADD
            x, y = geometry.cell_to_xy(int(cell[0]), int(cell[1]))
            marker.pose.position.x, marker.pose.position.y = x, y
            marker.pose.orientation.w = 1.0
            scale = geometry.resolution * (0.8 if kind == "robot" else 0.4)
            marker.scale.x = marker.scale.y = scale
            marker.scale.z = 0.2 * geometry.resolution
            hue = (i * 0.618) % 1.0
            marker.color.r, marker.color.g, marker.color.b = hue, 1.0 - hue, 0.5
            marker.color.a = 1.0 if kind == "robot" else 0.6
            array.markers.append(marker)
    return array


def main(argv: list[str] | None = None) -> int:
    """Run the simulator until the run ends; exit code 0 on success."""
    common.prepare_environment()
    args = sys.argv if argv is None else ["simulator"] + list(argv)
    rclpy.init(args=args)
    node = SimulatorNode()
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = common.SpinThread(executor).start()
    node.start()
    try:
        while not node.finished.wait(0.2):
            pass
        time.sleep(0.5)  # let the latched outcome reach late subscribers
    except KeyboardInterrupt:
        pass
    finally:
        spinner.stop()
        success = bool(node.outcome is not None and node.outcome.success)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0 if success else 1


if __name__ == "__main__":
    sys.exit(main())
