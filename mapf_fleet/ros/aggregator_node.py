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

import sys
import time

import numpy as np
from geometry_msgs.msg import PoseStamped
from mapf_fleet_interfaces.msg import FleetOutcome

from mapf_fleet.entry import one_line_errors
from mapf_fleet.fleet import parameters
from mapf_fleet.fleet.arbiter import check_pose, plan_robot_commands, ready_to_send
from mapf_fleet.fleet.lockstep import fleet_run
from mapf_fleet.fleet.record import Decisions
from mapf_fleet.grid.actions import STAY, actions_between
from mapf_fleet.ros import common, fleet_io
from mapf_fleet.ros.goals import GoalServer

PARAMETERS = parameters.AGGREGATOR  # name -> Param (fleet.parameters: the one table)


REJECT_LOG_PERIOD_S = 10.0
WAIT_LOG_PERIOD_S = 5.0


class StartupError(RuntimeError):
    """The fleet could not start (robots without a pose): one line, exit 2, no traceback."""


def arrival_warning(tick: int, robots: list[int], waited: float, timeout: float,
                    stopping: bool) -> str:
    """The warning for robots not at their waypoints when the tick's wait ended: the time it
    really waited (it used to say `arrival_timeout` whatever the wait), and why it ended early."""
    why = ("" if waited >= timeout else
           f" (the run is stopping; arrival_timeout {timeout:g} s)" if stopping else
           f" (arrival_timeout {timeout:g} s)")
    return (f"tick {tick}: robots {robots} not at their waypoints after {waited:.1f} s{why}")


class FleetStateAggregator(fleet_io.LockstepNode):
    NAME = "aggregator"
    PARAMETERS = PARAMETERS

    def __init__(self, **node_kwargs):
        super().__init__(**node_kwargs)
        self.grid = np.asarray(self.instance.grid, dtype=np.uint8)
        self.instance_goals = np.array(self.instance.goals, dtype=np.int64)
        self.positions = np.full((self.num_robots, 2), -1, dtype=np.int64)  # last valid cells
        self.waypoints: np.ndarray | None = None  # last commanded cell per robot
        self.run = None  # the FleetRun, once every robot reported its first pose
        self.rejected = 0  # every rejected pose message (not only those left at a tick's end)
        self.pose_conflicts = 0  # moments two robots reported one cell
        # the poses are guarded by (and notify) the ticker's condition, so the start-up and the
        # arrival waits see moves, heartbeats and poses alike
        self._cond = self.ticker.cond
        self._reported: dict[int, tuple[int, int]] = {}  # latest snapped cell per robot
        self._rejected_reason: dict[int, str] = {}
        self._rejected_in_tick: set[int] = set()
        self._accepted: dict[int, tuple[int, int]] = {}  # last accepted cell per robot
        self._logged_reject: dict[tuple[int, str], float] = {}  # (robot, reason) -> when logged
        self._heard: dict[int, float] = {}  # robot -> when its last pose message came
        self.silent: set[int] = set()  # robots reported silent (held as obstacles)
        for i in range(self.num_robots):
            self.create_subscription(PoseStamped, common.rel(common.pose_topic(i)),
                                     lambda msg, i=i: self._on_pose(i, msg),
                                     common.reliable_qos(10))
        self.channels.publish_map_and_goals(self.grid, self.instance_goals)
        # goals at run time; bound to the run once the robots have posed
        self.goals = GoalServer(self, None, self.lock, self.geometry, self.num_robots,
                                robot_actions=bool(self.params["robot_actions"]))
        # decision_timeout, arrival_timeout, progress_every apply from the next tick
        self._start_tick_thread()

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
            self._heard[robot_id] = time.monotonic()
            if robot_id in self.silent:
                self.silent.discard(robot_id)
                self.get_logger().info(f"robot {robot_id}: pose feed back")
            checked = check_pose(self.grid, self.geometry, x, y, self._accepted.get(robot_id))
            cell, reason = checked.cell, checked.reason
            if cell is None:
                self.rejected += 1
                self._rejected_in_tick.add(robot_id)
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

    def _check_silent(self) -> list[int]:
        """Robots whose feed went quiet past `pose_timeout` (reported once each); all silent."""
        timeout = float(self.params["pose_timeout"])
        now = time.monotonic()
        with self._cond:
            quiet = [i for i in range(self.num_robots)
                     if now - self._heard.get(i, now) > timeout]
            new = [i for i in quiet if i not in self.silent]
            self.silent.update(new)
        if new:
            self.get_logger().error(f"robots {new}: no pose for {timeout} s: held as obstacles "
                                    f"until their feed comes back")
        return sorted(self.silent)

    # ---- the tick loop (own thread) ----
    def _wait_for_poses(self, timeout: float) -> list[int]:
        """Wait for every robot's first valid pose, every policy node and the state's listeners
        (`state_heard_by_fleet`); progress every WAIT_LOG_PERIOD_S. The robots still without a
        pose (stopped: at once)."""
        deadline = time.monotonic() + timeout

        def posed_and_heard() -> bool:
            return bool((self.positions[:, 0] >= 0).all()) and self.state_heard_by_fleet()

        while not self.ticker.stopped:
            left = deadline - time.monotonic()
            unready = self.ticker.wait_ready(min(WAIT_LOG_PERIOD_S, max(left, 0.0)),
                                             also=posed_and_heard)
            with self._cond:
                unposed = np.flatnonzero(self.positions[:, 0] < 0).tolist()
            heard = self.state_heard_by_fleet()
            if (not unposed and not unready and heard) or left <= WAIT_LOG_PERIOD_S:
                break
            if not self.ticker.stopped:
                waiting = ([f"poses from robots {unposed}"] if unposed else []) + (
                    [f"the policy nodes of robots {unready}"] if unready else []) + (
                    [] if heard else ["every policy process (and a bag recorder) to hear the "
                                      "fleet state"])
                self.get_logger().info(f"waiting for {' and '.join(waiting)} "
                                       f"({max(left, 0):.0f} s left of startup_timeout "
                                       f"{timeout} s)")
        with self._cond:
            return np.flatnonzero(self.positions[:, 0] < 0).tolist()

    def _run(self):
        startup_timeout = float(self.params["startup_timeout"])
        unposed = self._wait_for_poses(startup_timeout)
        if self.ticker.stopped:
            self.outcome = FleetOutcome(
                episode=self.episode, success=False,
                summary=f"stopped at tick 0 while waiting for poses from robots {unposed}"
                if unposed else "stopped at tick 0 before the first tick")
            self.get_logger().info(self.outcome.summary)
            return
        if unposed:
            self.exit_code = 2
            raise StartupError(f"no valid pose from robots {unposed} within startup_timeout "
                               f"{startup_timeout} s: check their pose feeds "
                               f"({common.pose_topic(unposed[0])}, ...)")
        unready = self.ticker.unready()
        if unready:
            self.get_logger().warning(f"starting without ready robots {unready} "
                                      f"after {startup_timeout} s")
        with self.lock:
            starts = self.positions.copy()
            self.run = fleet_run(self.params, self.grid, starts, self.instance_goals,
                                 self.episode, ("rejected", "executed", "overridden", "late",
                                                "waypoints"), self.geometry)
            self.goals.bind(self.run)
        self.get_logger().info(f"all {self.num_robots} robots posed at "
                               f"{starts.tolist()}, conflict rule {self.conflict_rule}, "
                               f"task source {self.params['task_source']}")
        self.waypoints = starts.copy()
        self._heard = {i: time.monotonic() for i in range(self.num_robots)}
        self.run_ticks(self.run, summary_extra=self._summary_extra)

    def _summary_extra(self) -> str:
        self.run.recorder.record.update(pose_conflicts=self.pose_conflicts,
                                        rejected_poses=self.rejected,
                                        silent_robots=sorted(self.silent))
        silent = f", robots {sorted(self.silent)} silent" if self.silent else ""
        return (f", {self.rejected} rejected poses, {self.pose_conflicts} pose conflicts"
                f"{silent}")

    def _step(self, decisions: Decisions):
        """The real robots' move: command the arbitrated waypoints (followers once their cell is
        vacated), wait until the robots report their commanded cells (or `arrival_timeout`),
        then take their valid reported cells as the next positions. Silent robots (no pose for
        `pose_timeout`) are held like robots without a decision; when every robot is silent
        the run stops."""
        arrival_timeout = float(self.params["arrival_timeout"])
        silent = self._check_silent()
        if len(silent) == self.num_robots:
            self.get_logger().error(f"tick {decisions.tick}: every robot's pose feed is silent "
                                    f"(no pose for {self.params['pose_timeout']} s): the run "
                                    f"ends")
            self.ticker.stop()
        missing = sorted(set(decisions.missing) | set(silent))
        plan = plan_robot_commands(self.run.arbiter, self.positions.copy(), self.waypoints,
                                   decisions.rankings, missing)
        if plan.problems:
            self.get_logger().error(f"tick {decisions.tick}: unsafe commands "
                                    f"({'; '.join(plan.problems)}): every robot stays")
        if plan.stopped:
            self.get_logger().info(f"tick {decisions.tick}: robots {plan.stopped} would "
                                   f"rotate: they stay")
        late_live = np.flatnonzero(plan.late & ~np.isin(np.arange(self.num_robots),
                                                        silent)).tolist()
        if late_live:
            self.get_logger().warning(f"tick {decisions.tick}: robots {late_live} still in "
                                      f"transit: they hold both cells")
        commanded, executed, late = plan.waypoints.copy(), plan.executed.copy(), plan.late
        waited = time.monotonic()
        sent = self._dispatch_and_wait(commanded, arrival_timeout, skip=set(silent))
        waited = time.monotonic() - waited
        # never sent a new waypoint (its cell was not vacated in time): it stayed; a robot in
        # transit had its waypoint before and keeps it
        unsent = np.flatnonzero(~sent & ~late).tolist()
        unsent_live = [i for i in unsent if i not in silent]
        if unsent_live:
            self.get_logger().warning(f"tick {decisions.tick}: robots {unsent_live} waited for "
                                      f"their cell to be vacated: they stay")
        commanded[unsent] = self.positions[unsent]
        executed[unsent] = STAY
        self.waypoints = commanded
        with self._cond:
            arrived = np.array([tuple(commanded[i]) == tuple(self._reported.get(i, (-1, -1)))
                                for i in range(self.num_robots)])
            previous = self.positions.copy()
            # every robot with a pose rejected during the tick (a good pose may have come
            # after it) or still rejected now
            rejected = sorted(self._rejected_in_tick | set(self._rejected_reason))
            self._rejected_in_tick = set()
            for i, cell in self._reported.items():
                if i not in self._rejected_reason:
                    self.positions[i] = cell
            self.ticker.advance()
        # robots that went silent during the wait are reported as silent, not as late
        not_there = [i for i in np.flatnonzero(~arrived).tolist()
                     if i not in silent and i not in self.silent]
        if not_there:
            self.get_logger().warning(arrival_warning(decisions.tick, not_there, waited,
                                                      arrival_timeout, self.ticker.stopped))
        _, counts = np.unique(self.positions, axis=0, return_counts=True)
        overridden = np.flatnonzero((executed != decisions.actions)
                                    & ~plan.resolution.held).tolist()
        events = self.run.advance(
            decisions, self.positions, actions_between(previous, self.positions),
            collisions=int((counts[counts > 1]).sum()),
            rejected=rejected,
            executed=executed.tolist(), overridden=overridden,
            late=np.flatnonzero(late).tolist(), waypoints=commanded.tolist())
        self.channels.publish_goal_changes(self.run.goals, events)
        return events, overridden

    def _dispatch_and_wait(self, commanded: np.ndarray, timeout: float, skip=()) -> np.ndarray:
        """Send each robot its waypoint as soon as no other robot reports being in that cell,
        and wait until every robot (but `skip`: silent ones) reports its commanded cell, or
        `timeout`. bool (N,): the robots that were sent their waypoint."""
        deadline = time.monotonic() + timeout
        sent = np.zeros(self.num_robots, dtype=bool)
        awaited = [i for i in range(self.num_robots) if i not in skip]
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
                              for i in awaited)
                remaining = deadline - time.monotonic()
                if (arrived and sent[awaited].all()) or remaining <= 0 or self.ticker.stopped:
                    return sent
                self._cond.wait(min(remaining, 0.5))
                if self._newly_silent(awaited):
                    awaited = [i for i in awaited if i not in self.silent]

    def _newly_silent(self, awaited) -> bool:
        timeout = float(self.params["pose_timeout"])
        now = time.monotonic()
        quiet = [i for i in awaited if now - self._heard.get(i, now) > timeout]
        if quiet:
            self.silent.update(quiet)
            self.get_logger().error(f"robots {quiet}: no pose for {timeout} s: held as "
                                    f"obstacles until their feed comes back")
        return bool(quiet)

    def _publish_state(self, done: bool):
        goals = self.run.goals if self.run is not None else self.instance_goals
        last = self.run.last_actions if self.run is not None else \
            np.full(self.num_robots, -1, dtype=np.int64)
        self.channels.publish_state(self.positions, goals, last, done)


@one_line_errors("aggregator")
def main(argv: list[str] | None = None) -> int:
    """Run the aggregator until the run ends; exit code 0 on success."""
    return fleet_io.spin_until_finished(FleetStateAggregator, "aggregator", argv)


if __name__ == "__main__":
    sys.exit(main())
