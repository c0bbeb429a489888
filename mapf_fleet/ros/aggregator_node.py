"""FleetStateAggregator: real-robot mode. Instead of simulating, it builds the fleet state of each
tick from the robots' own pose feeds (`/robot_<i>/pose`, geometry_msgs/PoseStamped), so the
policy nodes run unchanged (same map, state, moves and waypoint topics as with the simulator).

Tick k: publish the fleet state of k; collect the robots' moves for k (a move missing after
`decision_timeout` counts as stay and is reported); each robot's commanded waypoint is its cell
plus its move (the cell its policy node sends to `/robot_<i>/waypoint`); wait until every robot
reports a pose in its commanded cell, or `arrival_timeout`; snap the poses to cells (map
resolution and origin) and publish tick k + 1. A pose off the grid or on an obstacle is
rejected with a log line naming the robot, the pose and the reason, and that robot holds its
last valid cell. Two robots reported in one cell are counted as a collision.

The map and the goals come from the same sources as the simulator's (instance YAML, MovingAI
files or a generated instance); the starts are the robots' first valid poses.
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
from visualization_msgs.msg import MarkerArray

from mapf_fleet.grid.actions import ACTION_DELTAS
from mapf_fleet.ros import common
from mapf_fleet.ros.instances import InstanceSource
from mapf_fleet.ros.simulator_node import fleet_markers

PARAMETERS = {
    "instance_file": ("", "instance YAML (grid rows, starts, goals): map and goals"),
    "map_file": ("", "MovingAI .map file (with scen_file)"),
    "scen_file": ("", "MovingAI .scen file (with map_file): goals"),
    "num_robots": (8, "robots to generate or to take from the .scen file"),
    "size": (16, "side of a generated square map"),
    "density": (0.3, "obstacle density of a generated map"),
    "seed": (0, "seed of a generated instance"),
    "max_steps": (256, "tick limit: the run fails when robots are not all on goal by then"),
    "decision_timeout": (5.0, "seconds to wait for a robot's move before it counts as stay"),
    "arrival_timeout": (10.0, "seconds to wait for robots to reach their waypoints"),
    "startup_timeout": (60.0, "seconds to wait for every robot's pose and policy node"),
    "resolution": (1.0, "metres per cell"),
    "origin_x": (0.0, "x of the map's corner (cell (0, 0) starts there)"),
    "origin_y": (0.0, "y of the map's corner"),
    "record_file": ("", "write the run's trajectory and outcome to this JSON file"),
    "progress_every": (10, "log progress every this many ticks"),
}


class FleetStateAggregator(Node):
    def __init__(self, **node_kwargs):
        super().__init__("mapf_aggregator", **node_kwargs)
        for name, (default, text) in PARAMETERS.items():
            self.declare_parameter(name, default, ParameterDescriptor(description=text))
        p = {name: self.get_parameter(name).value for name in PARAMETERS}
        self.params = p
        for name in ("decision_timeout", "arrival_timeout", "startup_timeout"):
            if not float(p[name]) > 0:
                raise ValueError(f"parameter {name} must be > 0, got {p[name]}")
        instance = InstanceSource(p["instance_file"], p["map_file"], p["scen_file"],
                                  int(p["num_robots"]), int(p["size"]), float(p["density"]),
                                  int(p["seed"])).load()
        self.grid = np.asarray(instance.grid, dtype=np.uint8)
        self.goals = np.array(instance.goals, dtype=np.int64)
        self.num_robots = len(self.goals)
        self.geometry = common.MapGeometry(float(p["resolution"]), float(p["origin_x"]),
                                           float(p["origin_y"]))
        self.episode = random.getrandbits(63)
        self.tick = 0
        self.positions = np.full((self.num_robots, 2), -1, dtype=np.int64)  # last valid cells
        self.last_actions = np.full(self.num_robots, -1, dtype=np.int64)
        self.rejected = 0
        self.outcome: FleetOutcome | None = None
        self.finished = threading.Event()
        self._cond = threading.Condition()
        self._reported: dict[int, tuple[int, int]] = {}  # latest snapped cell per robot
        self._rejected_reason: dict[int, str] = {}
        self._moves: dict[int, int] = {}
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
        self.goal_pubs = [self.create_publisher(PoseStamped, common.goal_topic(i),
                                                common.latched_qos())
                          for i in range(self.num_robots)]
        for i in range(self.num_robots):
            self.create_subscription(PoseStamped, common.pose_topic(i),
                                     lambda msg, i=i: self._on_pose(i, msg),
                                     common.reliable_qos(10))
        self.create_subscription(RobotMove, common.MOVES_TOPIC, self._on_move,
                                 common.reliable_qos(1000))
        self.create_subscription(RobotStatus, common.STATUS_TOPIC, self._on_status,
                                 common.reliable_qos(1000))
        self.map_pub.publish(common.grid_to_occupancy(self.grid, self.geometry))
        for i, pub in enumerate(self.goal_pubs):
            pub.publish(common.cell_pose(*self.goals[i], self.geometry))
        self.record = {"episode": self.episode, "positions": [], "actions": [], "missed": [],
                       "rejected": []}
        self._thread = threading.Thread(target=self._run_safely, name="aggregator", daemon=True)

    # ---- pose feeds ----
    def check_pose(self, robot_id: int, x: float, y: float) -> tuple[tuple[int, int] | None, str]:
        """(cell, "") for a pose on a free cell, else (None, reason)."""
        row, col = self.geometry.xy_to_cell(x, y)
        h, w = self.grid.shape
        if not (0 <= row < h and 0 <= col < w):
            return None, f"off the {h}x{w} grid (cell {row},{col})"
        if self.grid[row, col]:
            return None, f"on an obstacle (cell {row},{col})"
        return (row, col), ""

    def _on_pose(self, robot_id: int, msg: PoseStamped):
        x, y = float(msg.pose.position.x), float(msg.pose.position.y)
        cell, reason = self.check_pose(robot_id, x, y)
        with self._cond:
            if cell is None:
                raw = self.geometry.xy_to_cell(x, y)
                self._reported[robot_id] = raw  # it did move there: counts for arrival
                if self._rejected_reason.get(robot_id) != reason:
                    self.get_logger().error(
                        f"robot {robot_id}: pose rejected: x={x:.3f} y={y:.3f} is {reason}; "
                        f"the robot holds its last valid cell "
                        f"{tuple(int(v) for v in self.positions[robot_id])}")
                self._rejected_reason[robot_id] = reason
            else:
                self._reported[robot_id] = cell
                self._rejected_reason.pop(robot_id, None)
                if self.positions[robot_id, 0] < 0:
                    self.positions[robot_id] = cell  # first valid pose: the start
            self._cond.notify_all()

    def _on_move(self, msg: RobotMove):
        with self._cond:
            if msg.episode != self.episode or msg.tick != self.tick:
                return
            if msg.robot_id >= self.num_robots or msg.action > 4:
                self.get_logger().warning(f"ignored bad move {msg.robot_id}/{msg.action}")
                return
            self._moves[int(msg.robot_id)] = int(msg.action)
            self._cond.notify_all()

    def _on_status(self, msg: RobotStatus):
        with self._cond:
            if msg.robot_id < self.num_robots and msg.ready:
                self._ready[int(msg.robot_id)] = msg
                self._cond.notify_all()

    # ---- the tick loop (own thread) ----
    def start(self):
        self._thread.start()

    def _run_safely(self):
        try:
            self._run()
        except Exception as exc:
            self.get_logger().error(f"aggregator failed: {exc!r}")
            self.outcome = FleetOutcome(episode=self.episode, success=False,
                                        summary=f"aggregator failed: {exc!r}")
        finally:
            self.finished.set()

    def _wait_startup(self):
        n = self.num_robots
        deadline = time.monotonic() + float(self.params["startup_timeout"])
        with self._cond:
            while time.monotonic() < deadline:
                posed = (self.positions[:, 0] >= 0).all()
                ready = sum(1 for s in self._ready.values() if s.peers >= n)
                if posed and ready >= n:
                    break
                self._cond.wait(0.1)
            unposed = np.flatnonzero(self.positions[:, 0] < 0).tolist()
        if unposed:
            raise RuntimeError(f"no valid pose from robots {unposed} within "
                               f"{self.params['startup_timeout']} s")
        self.get_logger().info(f"all {n} robots posed at {self.positions.tolist()}")

    def _run(self):
        self._wait_startup()
        max_steps = int(self.params["max_steps"])
        decision_timeout = float(self.params["decision_timeout"])
        arrival_timeout = float(self.params["arrival_timeout"])
        collisions = missed = steps = 0
        missed_robots: set[int] = set()
        self.record["positions"].append(self.positions.tolist())
        started = time.monotonic()
        success = bool((self.positions == self.goals).all())
        while not success and steps < max_steps and rclpy.ok():
            self._publish_state(done=False)
            deadline = time.monotonic() + decision_timeout
            with self._cond:
                while len(self._moves) < self.num_robots and time.monotonic() < deadline:
                    self._cond.wait(max(0.0, deadline - time.monotonic()))
                moves, self._moves = dict(self._moves), {}
            missing = sorted(set(range(self.num_robots)) - set(moves))
            if missing:
                missed += len(missing)
                missed_robots.update(missing)
                self.get_logger().warning(f"tick {self.tick}: no decision from robots "
                                          f"{missing} within {decision_timeout} s: they stay")
            actions = np.array([moves.get(i, 0) for i in range(self.num_robots)], np.int64)
            commanded = self.positions + ACTION_DELTAS[actions]
            arrived = self._wait_arrival(commanded, arrival_timeout)
            late = np.flatnonzero(~arrived).tolist()
            if late:
                self.get_logger().warning(f"tick {self.tick}: robots {late} not at their "
                                          f"waypoints after {arrival_timeout} s")
            with self._cond:
                previous = self.positions.copy()
                rejected = sorted(self._rejected_reason)
                for i, cell in self._reported.items():
                    if i not in self._rejected_reason:
                        self.positions[i] = cell
                self.tick += 1
            moved = self.positions - previous
            self.last_actions = np.array([_action_of(d) for d in moved], dtype=np.int64)
            _, counts = np.unique(self.positions, axis=0, return_counts=True)
            collisions += int((counts[counts > 1]).sum())
            self.rejected += len(rejected)
            steps += 1
            on_goal = (self.positions == self.goals).all(1)
            success = bool(on_goal.all())
            self.record["actions"].append(actions.tolist())
            self.record["missed"].append(missing)
            self.record["rejected"].append(rejected)
            self.record["positions"].append(self.positions.tolist())
            self.progress_pub.publish(FleetProgress(
                episode=self.episode, tick=self.tick, max_steps=max_steps,
                num_robots=self.num_robots, on_goal=int(on_goal.sum()), collisions=collisions,
                missed_decisions=missed, missed_robots=missing))
            if steps % int(self.params["progress_every"]) == 0:
                self.get_logger().info(f"tick {self.tick}: {int(on_goal.sum())}/"
                                       f"{self.num_robots} on goal, {collisions} collisions")
        self._publish_state(done=True)
        on_goal = int((self.positions == self.goals).all(1).sum())
        summary = (f"{'success' if success else 'failure'}: {on_goal}/{self.num_robots} robots "
                   f"on goal after {steps} steps, {collisions} collisions, {missed} missed "
                   f"decisions, {self.rejected} rejected poses")
        self.outcome = FleetOutcome(
            episode=self.episode, success=success, steps=steps, num_robots=self.num_robots,
            collisions=collisions, missed_decisions=missed, missed_robots=sorted(missed_robots),
            summary=summary)
        self.outcome_pub.publish(self.outcome)
        self.get_logger().info(summary)
        if self.params["record_file"]:
            self.record.update(run_seconds=time.monotonic() - started, success=success,
                               steps=steps, collisions=collisions, missed_decisions=missed,
                               summary=summary)
            with open(self.params["record_file"], "w") as handle:
                json.dump(self.record, handle)

    def _wait_arrival(self, commanded: np.ndarray, timeout: float) -> np.ndarray:
        """bool (N,): robots whose latest reported cell is their commanded cell."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                arrived = np.array([tuple(commanded[i]) == tuple(self._reported.get(i, (-1, -1)))
                                    for i in range(self.num_robots)])
                remaining = deadline - time.monotonic()
                if arrived.all() or remaining <= 0:
                    return arrived
                self._cond.wait(remaining)

    def _publish_state(self, done: bool):
        stamp = self.get_clock().now().to_msg()
        msg = FleetState(episode=self.episode, tick=self.tick, done=done,
                         rows=self.positions[:, 0].tolist(), cols=self.positions[:, 1].tolist(),
                         goal_rows=self.goals[:, 0].tolist(), goal_cols=self.goals[:, 1].tolist(),
                         last_actions=self.last_actions.tolist())
        msg.header.stamp = stamp
        msg.header.frame_id = common.FRAME_ID
        self.state_pub.publish(msg)
        self.markers_pub.publish(fleet_markers(self.positions, self.goals, self.geometry, stamp))


def _action_of(delta) -> int:
    """The action whose move is `delta` (0 stay when none is: a robot that jumped or held)."""
    for action, move in enumerate(ACTION_DELTAS):
        if int(move[0]) == int(delta[0]) and int(move[1]) == int(delta[1]):
            return action
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run the aggregator until the run ends; exit code 0 on success."""
    common.prepare_environment()
    args = sys.argv if argv is None else ["aggregator"] + list(argv)
    rclpy.init(args=args)
    node = FleetStateAggregator()
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
