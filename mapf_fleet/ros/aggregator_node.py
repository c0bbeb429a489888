"""FleetStateAggregator: real-robot mode. Instead of simulating, it builds the fleet state of each
tick from the robots' own pose feeds (`/robot_<i>/pose`, geometry_msgs/PoseStamped), so the
policy nodes run unchanged (same map, state and moves topics as with the simulator). It is the
tick's arbiter: the only node that commands the robots (`/robot_<i>/waypoint`).

Tick k: publish the fleet state of k; collect the robots' ranked moves for k; arbitrate them
(`arbiter.TickArbiter`, `conflict_rule`) so that every robot is commanded to its own cell or an
adjacent free cell no other robot is commanded to, with no two robots trading cells:
- a robot whose decision is missing (after `decision_timeout`, reported) stays, unpushable;
- a robot that has not reached its last waypoint (the state's cell is not its waypoint) is in
  transit: it occupies both cells (held, its waypoint reserved) and keeps its old waypoint;
- a rotation (followers in a cycle) stays put; a follower gets its waypoint only once the robot
  in its target cell has reported leaving it (robots move at their own pace), see
  `arbiter.break_rotations` / `ready_to_send`; the commands are checked by
  `arbiter.unsafe_commands` (any breach: every robot stays, logged as an error).
Then wait until every robot reports a pose in its commanded cell, or `arrival_timeout` (a
follower still waiting then is told to stay: it never got its waypoint); snap the poses to
cells (map resolution and origin) and publish tick k + 1 with `last_actions` = the moves the
robots really made. A pose with a NaN / infinite coordinate, off the grid, on an obstacle or
more than one cell from the robot's last accepted cell (a jump) is rejected with one log line
naming the robot, the pose (field and value) and the reason (`arbiter.check_pose`), and that
robot holds its last valid cell (and is in transit from then on). Two robots reported in one
cell at any moment are counted (`pose_conflicts`) and logged; two in one cell at a tick are
counted as a collision.

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

from mapf_fleet.entry import one_line_errors
from mapf_fleet.grid.actions import STAY, actions_between
from mapf_fleet.ros import common, fleet_io
from mapf_fleet.fleet.arbiter import (TickArbiter, check_conflict_rule, check_pose,
                                    plan_robot_commands, ready_to_send)
from mapf_fleet.ros.lockstep import (INSTANCE_PARAMETERS, RUN_PARAMETERS, Decisions, FleetTicker,
                                     RunRecorder, instance_source, require_positive,
                                     set_parameters_result)

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


REJECT_LOG_PERIOD_S = 10.0


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
        self.waypoints: np.ndarray | None = None  # last commanded cell per robot
        self.conflict_rule = check_conflict_rule(str(p["conflict_rule"]))
        self.arbiter = TickArbiter(self.grid, self.goals, self.conflict_rule)
        self.rejected = 0
        self.pose_conflicts = 0  # moments two robots reported one cell
        self.outcome: FleetOutcome | None = None
        self.finished = threading.Event()

        self.ticker = FleetTicker(self.num_robots, self.episode)
        self.recorder = RunRecorder(self.episode, self.num_robots, self.goals,
                                    int(p["max_steps"]),
                                    series=("rejected", "executed", "overridden", "late",
                                            "waypoints"),
                                    conflict_rule=self.conflict_rule)
        # the poses are guarded by (and notify) the ticker's condition, so the start-up and the
        # arrival waits see moves, heartbeats and poses alike
        self._cond = self.ticker.cond
        self._reported: dict[int, tuple[int, int]] = {}  # latest snapped cell per robot
        self._rejected_reason: dict[int, str] = {}
        self._accepted: dict[int, tuple[int, int]] = {}  # last accepted cell per robot
        self._logged_reject: dict[tuple[int, str], float] = {}  # (robot, reason) -> when logged
        self.channels = fleet_io.FleetChannels(self, self.ticker, self.geometry)
        for i in range(self.num_robots):
            self.create_subscription(PoseStamped, common.rel(common.pose_topic(i)),
                                     lambda msg, i=i: self._on_pose(i, msg),
                                     common.reliable_qos(10))
        self.channels.publish_map_and_goals(self.grid, self.goals)
        # decision_timeout, arrival_timeout, progress_every apply from the next tick; any other
        # change at runtime is refused with the reason (lockstep.RUNTIME_PARAMETERS)
        self.add_on_set_parameters_callback(
            lambda parameters: set_parameters_result(self.params, parameters, self.get_logger()))
        self._thread = threading.Thread(
            target=fleet_io.run_reporting_failure, args=(self, "aggregator", self._run),
            name="aggregator", daemon=True)

    @property
    def tick(self) -> int:
        return self.ticker.tick

    # ---- pose feeds ----
    def check_pose(self, robot_id: int, x: float, y: float) -> tuple[tuple[int, int] | None, str]:
        """(cell, "") for a pose on a free cell at most one move from the robot's last accepted
        cell, else (None, reason): `arbiter.check_pose` (NaN / inf, off the grid, obstacle,
        jump)."""
        checked = check_pose(self.grid, self.geometry, x, y, self._accepted.get(robot_id))
        return checked.cell, checked.reason

    def _on_pose(self, robot_id: int, msg: PoseStamped):
        x, y = msg.pose.position.x, msg.pose.position.y
        with self._cond:
            checked = check_pose(self.grid, self.geometry, x, y, self._accepted.get(robot_id))
            cell, reason = checked.cell, checked.reason
            if cell is None:
                if checked.raw is not None:
                    self._reported[robot_id] = checked.raw  # it did move there: counts for arrival
                # one line per robot and reason (again after REJECT_LOG_PERIOD_S: a feed that
                # alternates good and bad poses does not flood the log)
                now = time.monotonic()
                if now - self._logged_reject.get((robot_id, reason), -1e9) > REJECT_LOG_PERIOD_S:
                    self._logged_reject[(robot_id, reason)] = now
                    self.get_logger().error(
                        f"robot {robot_id}: pose rejected: x={x:.3f} y={y:.3f}: {reason}; "
                        f"the robot holds its last valid cell "
                        f"{tuple(int(v) for v in self.positions[robot_id])}")
                self._rejected_reason[robot_id] = reason
            else:
                previous = self._reported.get(robot_id)
                self._reported[robot_id] = cell
                self._accepted[robot_id] = cell
                self._rejected_reason.pop(robot_id, None)
                if self.positions[robot_id, 0] < 0:
                    self.positions[robot_id] = cell  # first valid pose: the start
                elif previous != cell:
                    others = [j for j, c in self._reported.items() if c == cell and j != robot_id]
                    if others:
                        self.pose_conflicts += 1
                        self.get_logger().error(f"robot {robot_id} reported in cell {cell} "
                                                f"where robots {others} are")
            self._cond.notify_all()

    # ---- the tick loop (own thread) ----
    def start(self):
        self._thread.start()

    def _run(self):
        startup_timeout = float(self.params["startup_timeout"])
        subscribers = int(self.params["state_subscribers"])
        unready = self.ticker.wait_ready(
            startup_timeout, also=lambda: bool((self.positions[:, 0] >= 0).all())
            and self.channels.state_heard(subscribers))
        with self._cond:
            unposed = np.flatnonzero(self.positions[:, 0] < 0).tolist()
        if unposed and not self.ticker.stopped:
            raise RuntimeError(f"no valid pose from robots {unposed} within {startup_timeout} s")
        if unready:
            self.get_logger().warning(f"starting without ready robots {unready} "
                                      f"after {startup_timeout} s")
        self.get_logger().info(f"all {self.num_robots} robots posed at "
                               f"{self.positions.tolist()}, conflict rule {self.conflict_rule}")
        self.waypoints = self.positions.copy()
        self.outcome = fleet_io.run_lockstep(
            self, self.channels, self.recorder, self.positions.copy(), self._step,
            self._publish_state, decision_timeout=float(self.params["decision_timeout"]),
            progress_every=int(self.params["progress_every"]),
            record_file=self.params["record_file"], summary_extra=self._summary_extra,
            settings=self.params)

    def _summary_extra(self) -> str:
        self.recorder.record["pose_conflicts"] = self.pose_conflicts
        return f", {self.rejected} rejected poses, {self.pose_conflicts} pose conflicts"

    def _step(self, decisions: Decisions):
        """The real robots' move: command the arbitrated waypoints (followers once their cell is
        vacated), wait until the robots report their commanded cells (or `arrival_timeout`),
        then take their valid reported cells as the next positions."""
        arrival_timeout = float(self.params["arrival_timeout"])
        plan = plan_robot_commands(self.arbiter, self.positions.copy(), self.waypoints,
                                   decisions.preferences, decisions.missing)
        if plan.problems:
            self.get_logger().error(f"tick {decisions.tick}: unsafe commands "
                                    f"({'; '.join(plan.problems)}): every robot stays")
        if plan.stopped:
            self.get_logger().info(f"tick {decisions.tick}: robots {plan.stopped} would "
                                   f"rotate: they stay")
        if plan.late.any():
            self.get_logger().warning(f"tick {decisions.tick}: robots "
                                      f"{np.flatnonzero(plan.late).tolist()} still in transit: "
                                      f"they hold both cells")
        commanded, executed, late = plan.waypoints.copy(), plan.executed.copy(), plan.late
        sent = self._dispatch_and_wait(commanded, arrival_timeout)
        # never sent a new waypoint (its cell was not vacated in time): it stayed; a robot in
        # transit had its waypoint before and keeps it
        unsent = np.flatnonzero(~sent & ~late).tolist()
        if unsent:
            self.get_logger().warning(f"tick {decisions.tick}: robots {unsent} waited for their "
                                      f"cell to be vacated: they stay")
            commanded[unsent] = self.positions[unsent]
            executed[unsent] = STAY
        self.waypoints = commanded
        with self._cond:
            arrived = np.array([tuple(commanded[i]) == tuple(self._reported.get(i, (-1, -1)))
                                for i in range(self.num_robots)])
            previous = self.positions.copy()
            rejected = sorted(self._rejected_reason)
            for i, cell in self._reported.items():
                if i not in self._rejected_reason:
                    self.positions[i] = cell
            self.ticker.advance()
        if not arrived.all():
            self.get_logger().warning(f"tick {decisions.tick}: robots "
                                      f"{np.flatnonzero(~arrived).tolist()} not at their "
                                      f"waypoints after {arrival_timeout} s")
        self.last_actions = actions_between(previous, self.positions)
        _, counts = np.unique(self.positions, axis=0, return_counts=True)
        self.rejected += len(rejected)
        overridden = np.flatnonzero((executed != decisions.actions)
                                    & ~plan.resolution.held).tolist()
        return self.positions.copy(), int((counts[counts > 1]).sum()), {
            "rejected": rejected, "executed": executed.tolist(), "overridden": overridden,
            "late": np.flatnonzero(late).tolist(), "waypoints": commanded.tolist()}

    def _dispatch_and_wait(self, commanded: np.ndarray, timeout: float) -> np.ndarray:
        """Send each robot its waypoint as soon as no other robot reports being in that cell,
        and wait until every robot reports its commanded cell, or `timeout`. bool (N,): the
        robots that were sent their waypoint."""
        deadline = time.monotonic() + timeout
        sent = np.zeros(self.num_robots, dtype=bool)
        with self._cond:
            while True:
                # a robot whose pose is rejected may still be in its last valid cell
                unsure = {i: tuple(self.positions[i]) for i in self._rejected_reason}
                ready = ready_to_send(commanded, self._reported, np.flatnonzero(~sent).tolist(),
                                      unsure)
                if ready:
                    self.channels.publish_waypoints(commanded, ready)
                    sent[ready] = True
                arrived = all(tuple(commanded[i]) == tuple(self._reported.get(i, (-1, -1)))
                              for i in range(self.num_robots))
                remaining = deadline - time.monotonic()
                if (arrived and sent.all()) or remaining <= 0 or self.ticker.stopped:
                    return sent
                self._cond.wait(remaining)

    def _publish_state(self, done: bool):
        self.channels.publish_state(self.positions, self.goals, self.last_actions, done)


@one_line_errors("aggregator")
def main(argv: list[str] | None = None) -> int:
    """Run the aggregator until the run ends; exit code 0 on success."""
    return fleet_io.spin_until_finished(FleetStateAggregator, "aggregator", argv)


if __name__ == "__main__":
    sys.exit(main())
