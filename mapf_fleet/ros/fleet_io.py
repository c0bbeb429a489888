"""The ROS side the simulator and the aggregator share: their base class (`LockstepNode`:
parameters declared once from the table, instance, episode, ticker, topics, tick thread), the
fleet topics they publish and subscribe (`FleetChannels`: map, goals, state, markers, progress,
outcome, the robots' waypoints; moves, heartbeats), the tick loop's ROS outlet (`RosOutlet`; the
loop itself is the ROS-free `fleet.tick_loop.TickLoop`) and the process `main`. What differs
between the two nodes is the `step` they give the loop: how a tick's moves, arbitrated by
`arbiter.TickArbiter`, become the next positions.
"""

from __future__ import annotations

import random
import sys
import threading
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from mapf_fleet_interfaces.msg import (FleetOutcome, FleetProgress, FleetState, HubStatus,
                                       RobotMove, RobotMoves, RobotStatus)
from nav_msgs.msg import OccupancyGrid
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import SingleThreadedExecutor
from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from visualization_msgs.msg import Marker, MarkerArray

from mapf_fleet.fleet import parameters
from mapf_fleet.fleet.arbiter import check_conflict_rule
from mapf_fleet.fleet.lockstep import FleetTicker, instance_source, parameter_change_problem
from mapf_fleet.fleet.tick_loop import TickLoop
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
    """The fleet-level publishers and the move/heartbeat subscriptions (feeding `ticker`): the
    policy processes' batches (RobotMoves, HubStatus: one message per process) and the
    per-robot messages (RobotMove, RobotStatus: a policy with `per_robot_messages`, or any
    other sender)."""

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
        self._batches_sub = node.create_subscription(
            RobotMoves, common.rel(common.MOVE_BATCHES_TOPIC), self._on_moves,
            common.reliable_qos(1000))
        node.create_subscription(RobotStatus, common.rel(common.STATUS_TOPIC), ticker.on_status,
                                 common.reliable_qos(1000))
        node.create_subscription(HubStatus, common.rel(common.HUB_STATUS_TOPIC),
                                 ticker.on_hub_status, common.reliable_qos(100))

    def _on_move(self, msg: RobotMove):  # executor thread: store and notify only
        self._take_move(msg)
        # the executor takes one message per wait and rebuilds its wait set in Python for each
        # (the larger part of the simulator's tick at 512 robots: docs/results.md, "The
        # simulator's world side at 512 robots"): the moves already queued behind
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

    def _on_moves(self, msg: RobotMoves):  # executor thread: store and notify only
        """A policy process's moves of a tick, one message for all its robots."""
        warning = self.ticker.on_moves(msg)
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

    def publish_waypoints(self, cells, robots=None, changed_only: bool = False) -> None:
        """Command robots (all, or the ids in `robots`) to their cells (N, 2). `changed_only`:
        only the robots whose waypoint is not the one last sent (the topic is latched: a robot
        or a late subscriber still holds its current waypoint)."""
        stamp = self.node.get_clock().now().to_msg()
        cells = np.asarray(cells, dtype=np.int64)
        robots = range(len(cells)) if robots is None else robots
        sent = getattr(self, "_waypoints_sent", None)
        if changed_only and sent is not None and sent.shape == cells.shape:
            changed = (cells != sent).any(axis=1)
            robots = [i for i in robots if changed[i]]
        publish_cells(self.waypoint_pubs, cells, robots, self.geometry, stamp)
        if sent is None or sent.shape != cells.shape:
            sent = self._waypoints_sent = np.full_like(cells, -1)
        sent[list(robots)] = cells[list(robots)]

    def publish_state(self, positions, goals, last_actions, done: bool):
        """FleetState of the ticker's tick and the markers; returns the stamp used."""
        stamp = self.node.get_clock().now().to_msg()
        self.state_pub.publish(fleet_state_msg(self.ticker.episode, self.ticker.tick, positions,
                                               goals, last_actions, done, stamp))
        if self.markers_pub.get_subscription_count():  # built only for a viewer (RViz)
            self.markers_pub.publish(fleet_markers(positions, goals, self.geometry, stamp))
        return stamp


def publish_cells(publishers, cells, robots, geometry, stamp) -> None:
    """Publish cell `cells[i]` as a PoseStamped (map frame, `stamp`) on `publishers[i]` for each
    robot i of `robots`: one message object filled again for each (publish serialises it at
    once), since building a PoseStamped per robot cost as much as publishing it."""
    msg = common.cell_pose(0, 0, geometry, stamp)
    position = msg.pose.position
    for i in robots:
        position.x, position.y = geometry.cell_to_xy(int(cells[i][0]), int(cells[i][1]))
        publishers[i].publish(msg)


class RosOutlet:
    """The tick loop's `fleet.tick_loop.FleetOutlet` over ROS: the node's state publisher
    (`publish_state`, node-specific: the simulator also publishes the poses), the progress and
    outcome topics of `channels`, the node's logger."""

    def __init__(self, node, channels: FleetChannels, publish_state):
        self.node, self.channels, self._publish_state = node, channels, publish_state

    def publish_state(self, done: bool) -> None:
        self._publish_state(done=done)

    def publish_progress(self, progress: dict) -> None:
        self.channels.progress_pub.publish(FleetProgress(**progress))

    def publish_outcome(self, outcome: dict) -> None:
        self.channels.outcome_pub.publish(FleetOutcome(**outcome))

    def log(self, level: str, text: str) -> None:
        # one call site per level: rclpy refuses a call site (file, line) whose severity
        # changes between calls (ValueError), which killed the tick thread at its first warning
        logger = self.node.get_logger()
        if level == "info":
            logger.info(text)
        elif level == "warning":
            logger.warning(text)
        elif level == "error":
            logger.error(text)
        else:
            raise ValueError(f"RosOutlet.log: no such level {level!r} (info, warning, error)")


class LockstepNode(Node):
    """What the simulator and the aggregator share as nodes: their parameters (declared and
    checked from their table once), the instance they load, the episode, the conflict rule and
    the guidance they build their world with, the tick bookkeeping (`lockstep.FleetTicker`),
    the fleet topics (`FleetChannels`), the tick thread and the run of the ticks
    (`run_ticks`: the ROS-free `fleet.tick_loop.TickLoop`). A subclass sets NAME and
    PARAMETERS, builds its run and implements `_run` (the tick thread's body), a `step` and a
    `publish_state`."""

    NAME = ""
    PARAMETERS: dict = {}

    def __init__(self, **node_kwargs):
        super().__init__(f"mapf_{self.NAME}", **node_kwargs)
        p = self.params = declare_parameters(self, self.PARAMETERS)
        self.source = instance_source(p)
        self.instance = self.source.load()
        self.num_robots = self.instance.num_agents
        # a Nav2 map sets the metres of the map frame; else `resolution` (and the origin)
        self.geometry = common.MapGeometry(*(self.source.geometry() or (
            float(p["resolution"]), float(p.get("origin_x", 0.0)),
            float(p.get("origin_y", 0.0)))))
        self.episode = random.getrandbits(63)
        self.conflict_rule = check_conflict_rule(str(p["conflict_rule"]))
        # the guidance file (None: none) every distance of this fleet is to be read from
        self.guidance = parameters.resolve_guidance(str(p["guidance"]))
        self.outcome: FleetOutcome | None = None
        self.exit_code: int | None = None
        self.finished = threading.Event()
        self.lock = threading.RLock()  # the run: tick thread and goal inputs
        self.ticker = FleetTicker(self.num_robots, self.episode, int(p.get("start_tick", 0)))
        self.channels = FleetChannels(self, self.ticker, self.geometry)

    def _start_tick_thread(self) -> None:
        """The tick thread (runtime parameter changes from the next tick), not started."""
        self._thread = tick_thread(self, self.NAME, self.PARAMETERS)

    @property
    def tick(self) -> int:
        return self.ticker.tick

    @property
    def extra_nodes(self) -> list:
        return [self.goals.node]  # spun by their own executor (`spin_until_finished`)

    def start(self):
        self._thread.start()

    def state_heard_by_fleet(self) -> bool:
        """Tick 0's condition on the state's listeners (with every robot ready, and for the
        aggregator every pose): every process whose robots reported ready hears the state (a
        hub that has the map and its peers may not yet be matched by the state's publisher,
        and a state it does not hear is a tick its robots miss), at least `state_subscribers`
        do, and with `state_recorder` that node (`up --bag`'s recorder, which subscribes once
        it has matched every topic it records) is among them."""
        return self.channels.state_heard(
            max(int(self.params["state_subscribers"]), self.ticker.ready_hosts()),
            str(self.params["state_recorder"]))

    def run_ticks(self, run, summary_extra=lambda: "") -> FleetOutcome:
        """Tick `run` with `self._step` and `self._publish_state` until it ends
        (`fleet.tick_loop.TickLoop`, its docstring the specification); the outcome."""
        loop = TickLoop(run, self.ticker, self._step,
                        RosOutlet(self, self.channels, self._publish_state), lock=self.lock,
                        settings=self.params, goals=self.goals,
                        record_file=self.params["record_file"], summary_extra=summary_extra,
                        keep_going=rclpy.ok)
        self.outcome = FleetOutcome(**loop.run())
        return self.outcome


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
