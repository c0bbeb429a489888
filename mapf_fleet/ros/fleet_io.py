"""The ROS side the simulator and the aggregator share: parameter declaration, the fleet topics
they publish and subscribe (map, goals, state, markers, progress, outcome, the robots' waypoints;
moves, heartbeats), the lockstep tick loop, the tick thread and the process `main`. What differs
between the two nodes is the `step` they give `run_lockstep`: how a tick's moves, arbitrated by
`arbiter.TickArbiter`, become the next positions.
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from mapf_fleet_interfaces.msg import (FleetOutcome, FleetProgress, FleetState, RobotMove,
                                       RobotStatus)
from nav_msgs.msg import OccupancyGrid
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import SingleThreadedExecutor
from rclpy.exceptions import InvalidHandle
from visualization_msgs.msg import Marker, MarkerArray

from mapf_fleet.fleet import parameters
from mapf_fleet.fleet.lockstep import FleetTicker, parameter_change_problem
from mapf_fleet.ros import common


def declare_parameters(node, table: dict) -> dict:
    """Declare the parameters of `table` (fleet.parameters: name -> Param) on `node` and check
    them (ValueError, one line, for the first refused); {name: value}."""
    for name, param in table.items():
        when = "changeable at run time" if param.runtime else "read at start-up"
        node.declare_parameter(name, param.default,
                               ParameterDescriptor(description=f"{param.description} ({when})"))
    values = {name: node.get_parameter(name).value for name in table}
    return parameters.check_values(table, values)


def set_parameters_result(params: dict, parameters, table: dict, logger=None):
    """For a node's `add_on_set_parameters_callback`: apply the changes to `params` (the dict
    the tick loop reads every tick) when all of them are allowed by the node's parameter
    `table`, else refuse them all with the reasons (rcl_interfaces SetParametersResult)."""
    problems = [p for p in (parameter_change_problem(q.name, q.value, table)
                            for q in parameters) if p]
    if problems:
        return SetParametersResult(successful=False, reason="; ".join(problems))
    for parameter in parameters:
        if logger is not None and params[parameter.name] != parameter.value:
            logger.info(f"parameter {parameter.name}: {params[parameter.name]} -> "
                        f"{parameter.value} (from the next tick)")
        params[parameter.name] = table[parameter.name].coerce(parameter.value)
    return SetParametersResult(successful=True)


def fleet_state_msg(episode: int, tick: int, positions, goals, last_actions, done: bool,
                    stamp) -> FleetState:
    """The FleetState of a tick: (N, 2) cells and goals, the last actions, stamped in the map
    frame."""
    msg = FleetState(episode=episode, tick=tick, done=done,
                     rows=positions[:, 0].tolist(), cols=positions[:, 1].tolist(),
                     goal_rows=goals[:, 0].tolist(), goal_cols=goals[:, 1].tolist(),
                     last_actions=np.asarray(last_actions).tolist())
    msg.header.stamp = stamp
    msg.header.frame_id = common.FRAME_ID
    return msg


class FleetChannels:
    """The fleet-level publishers and the move/heartbeat subscriptions (feeding `ticker`)."""

    def __init__(self, node, ticker: FleetTicker, geometry: common.MapGeometry):
        self.node = node
        self.ticker = ticker
        self.geometry = geometry
        n = ticker.num_robots
        self.map_pub = node.create_publisher(OccupancyGrid, common.rel(common.MAP_TOPIC),
                                             common.latched_qos())
        self.state_pub = node.create_publisher(FleetState, common.rel(common.STATE_TOPIC),
                                               common.reliable_qos(10))
        self.progress_pub = node.create_publisher(FleetProgress, common.rel(common.PROGRESS_TOPIC),
                                                  common.reliable_qos(10))
        self.outcome_pub = node.create_publisher(FleetOutcome, common.rel(common.OUTCOME_TOPIC),
                                                 common.latched_qos())
        self.markers_pub = node.create_publisher(MarkerArray, common.rel(common.MARKERS_TOPIC),
                                                 common.reliable_qos(2))
        quiet = common.quiet_publisher_events()  # per-robot publishers: keep the wait set small
        self.goal_pubs = [node.create_publisher(PoseStamped, common.rel(common.goal_topic(i)),
                                                common.latched_qos(), event_callbacks=quiet)
                          for i in range(n)]
        # the arbiter commands the robots: latched, so a robot whose subscription matches late
        # (discovery still running at tick 0, a restarted driver) still gets its current waypoint
        self.waypoint_pubs = [node.create_publisher(PoseStamped,
                                                    common.rel(common.waypoint_topic(i)),
                                                    common.latched_qos(1), event_callbacks=quiet)
                              for i in range(n)]
        self._moves_sub = node.create_subscription(RobotMove, common.rel(common.MOVES_TOPIC),
                                                   self._on_move, common.reliable_qos(1000))
        node.create_subscription(RobotStatus, common.rel(common.STATUS_TOPIC), ticker.on_status,
                                 common.reliable_qos(1000))

    def _on_move(self, msg: RobotMove):  # executor thread: store and notify only
        self._take_move(msg)
        # the executor takes one message per wait and rebuilds its wait set in Python for each
        # (about 0.2 ms a move, 100 ms a tick at 512 robots): the moves already queued behind
        # this one are taken here, in the order the executor would take them (at most two
        # ticks' worth: a tick's moves and as many stale ones; the rest waits for the next wait)
        sub = self._moves_sub
        for _ in range(2 * self.ticker.num_robots):
            try:
                with sub.handle:
                    taken = sub.handle.take_message(sub.msg_type, sub.raw)
            except InvalidHandle:  # destroyed under us: the node is shutting down
                return
            if taken is None:
                return
            self._take_move(taken[0])

    def _take_move(self, msg: RobotMove) -> None:
        warning = self.ticker.on_move(msg)
        if warning:
            self.node.get_logger().warning(warning)

    def state_heard(self, subscribers: int, recorder: str = "") -> bool:
        """Whether the fleet state has at least `subscribers` matched subscribers and, with
        `recorder`, a subscription of the node of that name (a count alone is reached by any
        other subscriber, e.g. a viewer, while the recorder still discovers the fleet)."""
        if subscribers > 0 and self.state_pub.get_subscription_count() < subscribers:
            return False
        if not recorder:
            return True
        topic = self.state_pub.topic_name
        found = [e for e in self.node.get_subscriptions_info_by_topic(topic)
                 if e.node_name == recorder]
        return bool(found) and self.state_pub.get_subscription_count() >= max(subscribers, 1)

    def publish_map_and_goals(self, grid, goals) -> None:
        self.map_pub.publish(common.grid_to_occupancy(np.asarray(grid), self.geometry))
        self._goals_sent = np.array(goals, dtype=np.int64)
        for i, pub in enumerate(self.goal_pubs):
            pub.publish(common.cell_pose(*goals[i], self.geometry))

    def publish_goal_changes(self, goals, events=()) -> None:
        """Each robot's latched goal, again for the robots whose goal changed since (run-time
        goals, lifelong goals, idle robots whose goal is where they stand)."""
        goals = np.asarray(goals, dtype=np.int64)
        changed = np.flatnonzero((goals != self._goals_sent).any(axis=1)).tolist()
        for i in changed:
            self.goal_pubs[i].publish(common.cell_pose(*goals[i], self.geometry))
        self._goals_sent = goals.copy()

    def publish_waypoints(self, cells, robots=None) -> None:
        """Command robots (all, or the ids in `robots`) to their cells (N, 2)."""
        stamp = self.node.get_clock().now().to_msg()
        for i in range(len(cells)) if robots is None else robots:
            self.waypoint_pubs[i].publish(common.cell_pose(int(cells[i][0]), int(cells[i][1]),
                                                           self.geometry, stamp))

    def publish_state(self, positions, goals, last_actions, done: bool):
        """FleetState of the ticker's tick and the markers; returns the stamp used."""
        stamp = self.node.get_clock().now().to_msg()
        self.state_pub.publish(fleet_state_msg(self.ticker.episode, self.ticker.tick, positions,
                                               goals, last_actions, done, stamp))
        if self.markers_pub.get_subscription_count():  # built only for a viewer (RViz)
            self.markers_pub.publish(fleet_markers(positions, goals, self.geometry, stamp))
        return stamp


IDLE_STATE_PERIOD_S = 1.0  # an idle fleet republishes its state this often


def run_lockstep(node, channels: FleetChannels, run, step, publish_state, *, lock,
                 goals=None, decision_timeout: float, tick_period: float = 0.0,
                 progress_every: int = 10, record_file: str = "",
                 summary_extra=lambda: "", settings: dict | None = None) -> FleetOutcome:
    """Tick `run` (a `fleet.run.FleetRun`) until it is finished (every robot on its goal for a
    one-shot instance, the tick limit, every task done) or stopped.

    Each tick: `publish_state(done=False)`, collect the moves, then `step(decisions) ->
    (events, overridden robot ids)` makes the next tick (it must call `ticker.advance()` and
    `run.advance`, under `lock`); the goal events go to `goals` (`ros.goals.GoalServer`, also
    the action feedback), progress is published and logged every `progress_every` ticks; the
    record is written once at the first tick (marked incomplete) and every tick goes to its
    journal as it ends (a killed process leaves what it ran). A continuous fleet with nothing
    to do (`run.waiting`: every robot idle) does not tick: it waits for a goal. At the end: the
    final state, the outcome (published, latched; `summary_extra()` is appended to its summary)
    and the record. `ticker.stop()` (a signal, a failed callback) ends the run before the next
    tick: the outcome is "stopped at tick k" and the record is written all the same.
    """
    logger = node.get_logger()
    ticker = channels.ticker
    published, published_at = None, 0.0  # the tick whose state is out, and when
    checkpointed = False  # the record is written (incomplete) at the first tick only
    run.recorder.started = time.monotonic()  # run_seconds count from the first tick, not start-up
    if record_file:  # every tick kept as it ends, whatever happens to this process
        # a tick leaves memory once in the journal: the record is streamed from it at the end
        run.recorder.open_journal(record_file, keep_ticks=False)
    while not run.finished() and rclpy.ok() and not ticker.stopped:
        if run.waiting and goals is not None:
            if published != run.tick or time.monotonic() - published_at > IDLE_STATE_PERIOD_S:
                # the state of this tick goes out (viewers and clients see the fleet; the robots
                # decide it once, their moves wait in the ticker until a goal comes; the same
                # tick again is ignored by the hubs and keeps their episode binding alive)
                if published != run.tick:
                    logger.info(f"tick {run.tick}: every robot idle: waiting for goals")
                publish_state(done=False)
                published, published_at = run.tick, time.monotonic()
            goals.request_signal.wait(0.2)
            with lock:
                events = run.apply_requests()
                goals.on_tick(events)
            continue
        started = time.monotonic()
        if settings is not None:  # the node's parameters, changed at runtime (lockstep)
            decision_timeout = float(settings.get("decision_timeout", decision_timeout))
            tick_period = float(settings.get("tick_period", tick_period))
            progress_every = int(settings.get("progress_every", progress_every))
        if published != run.tick:
            publish_state(done=False)
            published = run.tick
        decisions = ticker.collect(decision_timeout)
        if ticker.stopped:
            break  # this tick is not played: the record stays consistent
        if decisions.missing:
            logger.warning(run.recorder.missing_text(decisions, decision_timeout))
        with lock:
            events, overridden = step(decisions)
            progress = run.progress(decisions.missing)
            if goals is not None:
                # the estimated time counts a tick as long as it is paced (tick_period)
                goals.on_tick(events, overridden,
                              max(time.monotonic() - started, tick_period))
        for event in events:
            if event.event not in ("reached", "assigned") or run.num_robots <= 16:
                logger.info(event.text())
        channels.progress_pub.publish(FleetProgress(**progress))
        if run.steps % progress_every == 0:
            logger.info(run.progress_text())
        # the record's head for a process that dies before the end, written once: the journal
        # holds every tick after it and `read_record` joins them, where rewriting the whole
        # record would cost more each time as the run grows
        if record_file and not checkpointed:
            run.recorder.checkpoint(record_file, run.tick)
            checkpointed = True
        if tick_period > 0:
            time.sleep(max(0.0, tick_period - (time.monotonic() - started)))
    publish_state(done=True)
    stopped_at = run.tick if ticker.stopped and not run.finished() else None
    with lock:
        reason = (f"the run ended at tick {run.tick}" if stopped_at is None
                  else f"the run was stopped at tick {run.tick}")
        events = run.abort_active(reason) if run.tasks.continuous else []
        if goals is not None:
            goals.on_tick(events)
            goals.close(reason)
        outcome = FleetOutcome(**run.finish(extra=summary_extra(), stopped_at=stopped_at))
    channels.outcome_pub.publish(outcome)
    logger.info(outcome.summary)
    if record_file:
        run.recorder.write(record_file)
        run.recorder.close_journal(record_file)
    return outcome


def tick_thread(node, name: str, table: dict) -> threading.Thread:
    """The simulator's or the aggregator's tick thread (not started) running `node._run`, after
    registering its runtime parameter changes: checked against `table`, applied to
    `node.params` from the next tick, refused with the reason otherwise (fleet.parameters:
    runtime)."""
    node.add_on_set_parameters_callback(
        lambda changes: set_parameters_result(node.params, changes, table, node.get_logger()))
    return threading.Thread(target=run_reporting_failure, args=(node, name, node._run), name=name,
                            daemon=True)


def run_reporting_failure(node, name: str, run) -> None:
    """Target of a node's tick thread: `run()`, turning an exception into a failed
    `node.outcome` (so the process lives to report it), and set `node.finished` in any case."""
    try:
        run()
    except Exception as exc:  # keep the process alive long enough to report
        if getattr(node, "exit_code", None) is not None:
            # a failure the node explains in one line (exit code set: no traceback)
            node.get_logger().error(f"{name}: {exc}")
            node.outcome = FleetOutcome(episode=node.episode, success=False,
                                        summary=f"{name}: {exc}")
            return
        import traceback

        node.get_logger().error(f"{name} failed: {exc!r}\n{traceback.format_exc().rstrip()}")
        node.outcome = FleetOutcome(episode=node.episode, success=False,
                                    summary=f"{name} failed: {exc!r}")
    finally:
        node.finished.set()


def spin_until_finished(make_node, name: str, argv: list[str] | None = None) -> int:
    """Process main of a lockstep node: spin it, run its ticks, exit 0 on success, 1 on failure.

    SIGINT / SIGTERM (at any time, start-up included) stop the run: the outcome "stopped at tick
    k" is published and the record written, then the process exits 130 / 143; a second signal
    exits within a second. A callback that raises (logged by `SpinThread` with its traceback) stops the
    run the same way and the process exits 1."""
    common.prepare_environment()
    signals = common.init_process(sys.argv if argv is None else [name] + list(argv))
    node = spinner = None
    extra_spinners = []
    try:
        # a signal during start-up (imports, init, the node's set-up) is acted on in the loop:
        # the run stops before tick 0, with its outcome and record all the same
        node = make_node()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        spinner = common.SpinThread(executor).start()
        # the goal inputs (per-robot goal_pose, actions; `ros.goals`) on their own executor, so
        # their entities do not slow the tick's (every robot's move, each tick)
        for extra in getattr(node, "extra_nodes", []):
            extra_executor = SingleThreadedExecutor()
            extra_executor.add_node(extra)
            extra_spinners.append(common.SpinThread(extra_executor).start())
        node.start()
        while not node.finished.wait(0.2):
            if signals.requested or spinner.error is not None or any(
                    extra.error is not None for extra in extra_spinners):
                node.ticker.stop()
            if signals.forced:  # a second signal: one more second for the record, then exit
                node.finished.wait(1.0)
                break
        if node.finished.is_set() and not signals.requested:
            time.sleep(0.5)  # let the latched outcome reach late subscribers
    finally:
        for extra in extra_spinners:
            extra.stop()
        if spinner is not None:
            spinner.stop()
        if node is not None:
            for extra in getattr(node, "extra_nodes", []):
                extra.destroy_node()
            node.destroy_node()
        rclpy.try_shutdown()
        signals.restore()
    if signals.requested:
        return signals.exit_code
    if getattr(node, "exit_code", None) is not None:
        return node.exit_code
    if spinner.error is not None or any(extra.error is not None for extra in extra_spinners):
        return 1
    return 0 if node.outcome is not None and node.outcome.success else 1


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
