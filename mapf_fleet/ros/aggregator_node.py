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
files or a generated instance); the starts are the robots' first valid poses. The tick
bookkeeping it shares with the simulator is in `lockstep` (plain Python) and `fleet_io`.
"""

from __future__ import annotations

import random
import sys
import threading
import time

import numpy as np
from geometry_msgs.msg import PoseStamped
from mapf_fleet_interfaces.msg import FleetOutcome
from rclpy.node import Node

from mapf_fleet.grid.actions import ACTION_DELTAS
from mapf_fleet.ros import common, fleet_io
from mapf_fleet.ros.lockstep import (INSTANCE_PARAMETERS, RUN_PARAMETERS, Decisions, FleetTicker,
                                     RunRecorder, instance_source, require_positive)

PARAMETERS = {
    **INSTANCE_PARAMETERS,
    "instance_file": ("", "instance YAML (grid rows, starts, goals): map and goals"),
    "scen_file": ("", "MovingAI .scen file (with map_file): goals"),
    **RUN_PARAMETERS,
    "startup_timeout": (60.0, "seconds to wait for every robot's pose and policy node"),
    "resolution": (1.0, "metres per cell"),
    "arrival_timeout": (10.0, "seconds to wait for robots to reach their waypoints"),
    "origin_x": (0.0, "x of the map's corner (cell (0, 0) starts there)"),
    "origin_y": (0.0, "y of the map's corner"),
}


class FleetStateAggregator(Node):
    def __init__(self, **node_kwargs):
        super().__init__("mapf_aggregator", **node_kwargs)
        p = self.params = fleet_io.declare_parameters(self, PARAMETERS)
        require_positive(p, ["decision_timeout", "arrival_timeout", "startup_timeout"])
        instance = instance_source(p).load()
        self.grid = np.asarray(instance.grid, dtype=np.uint8)
        self.goals = np.array(instance.goals, dtype=np.int64)
        self.num_robots = len(self.goals)
        self.geometry = common.MapGeometry(float(p["resolution"]), float(p["origin_x"]),
                                           float(p["origin_y"]))
        self.episode = random.getrandbits(63)
        self.positions = np.full((self.num_robots, 2), -1, dtype=np.int64)  # last valid cells
        self.last_actions = np.full(self.num_robots, -1, dtype=np.int64)
        self.rejected = 0
        self.outcome: FleetOutcome | None = None
        self.finished = threading.Event()

        self.ticker = FleetTicker(self.num_robots, self.episode)
        self.recorder = RunRecorder(self.episode, self.num_robots, self.goals,
                                    int(p["max_steps"]), series=("rejected",))
        # the poses are guarded by (and notify) the ticker's condition, so the start-up and the
        # arrival waits see moves, heartbeats and poses alike
        self._cond = self.ticker.cond
        self._reported: dict[int, tuple[int, int]] = {}  # latest snapped cell per robot
        self._rejected_reason: dict[int, str] = {}
        self.channels = fleet_io.FleetChannels(self, self.ticker, self.geometry)
        for i in range(self.num_robots):
            self.create_subscription(PoseStamped, common.pose_topic(i),
                                     lambda msg, i=i: self._on_pose(i, msg),
                                     common.reliable_qos(10))
        self.channels.publish_map_and_goals(self.grid, self.goals)
        self._thread = threading.Thread(
            target=fleet_io.run_reporting_failure, args=(self, "aggregator", self._run),
            name="aggregator", daemon=True)

    @property
    def tick(self) -> int:
        return self.ticker.tick

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

    # ---- the tick loop (own thread) ----
    def start(self):
        self._thread.start()

    def _run(self):
        startup_timeout = float(self.params["startup_timeout"])
        unready = self.ticker.wait_ready(startup_timeout,
                                         also=lambda: bool((self.positions[:, 0] >= 0).all()))
        with self._cond:
            unposed = np.flatnonzero(self.positions[:, 0] < 0).tolist()
        if unposed:
            raise RuntimeError(f"no valid pose from robots {unposed} within {startup_timeout} s")
        if unready:
            self.get_logger().warning(f"starting without ready robots {unready} "
                                      f"after {startup_timeout} s")
        self.get_logger().info(f"all {self.num_robots} robots posed at {self.positions.tolist()}")
        self.outcome = fleet_io.run_lockstep(
            self, self.channels, self.recorder, self.positions.copy(), self._step,
            self._publish_state, decision_timeout=float(self.params["decision_timeout"]),
            progress_every=int(self.params["progress_every"]),
            record_file=self.params["record_file"],
            summary_extra=lambda: f", {self.rejected} rejected poses")

    def _step(self, decisions: Decisions):
        """The real robots' move: wait until they report their commanded cells (or
        `arrival_timeout`), then take their valid reported cells as the next positions."""
        arrival_timeout = float(self.params["arrival_timeout"])
        commanded = self.positions + ACTION_DELTAS[decisions.actions]
        arrived = self._wait_arrival(commanded, arrival_timeout)
        late = np.flatnonzero(~arrived).tolist()
        if late:
            self.get_logger().warning(f"tick {decisions.tick}: robots {late} not at their "
                                      f"waypoints after {arrival_timeout} s")
        with self._cond:
            previous = self.positions.copy()
            rejected = sorted(self._rejected_reason)
            for i, cell in self._reported.items():
                if i not in self._rejected_reason:
                    self.positions[i] = cell
            self.ticker.advance()
        moved = self.positions - previous
        self.last_actions = np.array([_action_of(d) for d in moved], dtype=np.int64)
        _, counts = np.unique(self.positions, axis=0, return_counts=True)
        self.rejected += len(rejected)
        return self.positions.copy(), int((counts[counts > 1]).sum()), {"rejected": rejected}

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
        self.channels.publish_state(self.positions, self.goals, self.last_actions, done)


def _action_of(delta) -> int:
    """The action whose move is `delta` (0 stay when none is: a robot that jumped or held)."""
    for action, move in enumerate(ACTION_DELTAS):
        if int(move[0]) == int(delta[0]) and int(move[1]) == int(delta[1]):
            return action
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run the aggregator until the run ends; exit code 0 on success."""
    return fleet_io.spin_until_finished(FleetStateAggregator, "aggregator", argv)


if __name__ == "__main__":
    sys.exit(main())
