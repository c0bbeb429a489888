"""Goals at run time over ROS: the adapter between a node that owns a `fleet.run.FleetRun` (the
simulator, or the real-robot aggregator) and what ROS users send goals with.

- per robot `robot_<i>/goal_pose` (geometry_msgs/PoseStamped, map frame, metres; RViz's "2D
  Goal Pose" tool and Nav2's bt_navigator use this relative name, so it lands under the fleet
  namespace);
- per robot the action `robot_<i>/navigate_to_pose` (`mapf_fleet_interfaces/action/
  NavigateToPose`, Nav2's shape): feedback once per tick (current pose, distance remaining along
  the shortest path in metres, navigation time, estimated time = remaining cells x the measured
  seconds per tick, overridden moves as "recoveries"); result reached / aborted (preempted by a
  new goal, the run ended) / cancelled; cancel holds the robot on its cell (with
  `robot_actions`, which large fleets leave out: each server is 8 DDS endpoints);
- the fleet's action `fleet/navigate_to_pose` (`NavigateRobotToPose`): the same with the robot
  named in the goal, one server whatever the fleet's size;
- `fleet/submit_tasks` (`SubmitTasks.srv`): many goals or pick-up/drop-off tasks at once, for a
  named robot or the nearest idle one (the task file format, `fleet.tasks.parse_tasks`), queued
  whole or not at all;
- `fleet/cancel_goal` (`CancelRobotGoal.srv`): a robot's goal cancelled however it was given (an
  action's, a goal_pose, a task, the task source's): it holds its cell; one service whatever the
  fleet's size;
- `fleet/goal_events` (`GoalEvent`): every goal change, with the reason of each rejection.

A request is checked at once (`FleetRun.goal_problem`: robot, map, obstacle, reachability,
another robot headed there; here also NaN / infinite coordinates and the frame) and refused with
one log line naming robot and value; the run goes on. Accepted goals take effect at the next tick
boundary (`FleetRun`). These entities live on their own node ("mapf_goals"), spun by its own
executor thread, so the per-robot subscriptions and action servers do not slow the tick's
executor (which handles every robot's move each tick).
"""

from __future__ import annotations

import functools
import math
import threading
import time

from geometry_msgs.msg import PoseStamped
from mapf_fleet_interfaces.action import NavigateRobotToPose, NavigateToPose
from mapf_fleet_interfaces.msg import GoalEvent as GoalEventMsg
from mapf_fleet_interfaces.srv import CancelRobotGoal, SubmitTasks
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.node import Node
from rclpy.task import Future

from mapf_fleet.fleet.record import GoalEvent
from mapf_fleet.fleet.tasks import TaskFileError, parse_tasks
from mapf_fleet.ros import common

GOAL_EVENTS_TOPIC = common.GOAL_EVENTS_TOPIC
SUBMIT_TASKS_SERVICE = "/fleet/submit_tasks"
CANCEL_GOAL_SERVICE = "/fleet/cancel_goal"  # CancelRobotGoal: any robot's goal, however given
FLEET_NAVIGATE_ACTION = "/fleet/navigate_to_pose"  # NavigateRobotToPose: the robot in the goal
ACCEPTED_FRAMES = ("", common.FRAME_ID)  # an empty frame is read as the map frame (RViz sets it)


def goal_pose_topic(robot_id: int) -> str:
    return f"{common.robot_ns(robot_id)}/goal_pose"


def navigate_action(robot_id: int) -> str:
    return f"{common.robot_ns(robot_id)}/navigate_to_pose"


def pose_goal_cell(msg: PoseStamped, geometry) -> tuple[tuple[int, int] | None, str]:
    """(cell, "") of a goal pose, or (None, why not): coordinates must be finite numbers in the
    map frame (the grid checks come from `FleetRun.goal_problem`)."""
    frame = msg.header.frame_id
    if frame not in ACCEPTED_FRAMES:
        return None, f"frame {frame!r} is not the map frame {common.FRAME_ID!r}"
    x, y = msg.pose.position.x, msg.pose.position.y
    for name, value in (("pose.position.x", x), ("pose.position.y", y)):
        if not math.isfinite(value):
            return None, f"{name} is {value!r}, not a finite number"
    return tuple(int(v) for v in geometry.xy_to_cell(x, y)), ""


class _ActionGoal:
    """One accepted navigate_to_pose goal and the future its execute coroutine awaits."""

    def __init__(self, handle, robot: int, cell, started_tick: int, action=NavigateToPose):
        self.handle = handle
        self.action = action  # NavigateToPose or NavigateRobotToPose: its Result and Feedback
        self.robot = robot
        self.cell = cell
        self.started_tick = started_tick
        self.started = time.monotonic()
        self.future = Future()
        self.recoveries = 0


def goal_event_msg(episode: int, e: GoalEvent) -> GoalEventMsg:
    """The GoalEvent message of a goal event of the core (fleet.record.GoalEvent)."""
    msg = GoalEventMsg(episode=episode, tick=int(e.tick), robot_id=int(e.robot), event=e.event,
                       source=e.source, goal_id=e.goal_id, reason=e.reason,
                       has_cell=e.cell is not None)
    if e.cell is not None:
        msg.row, msg.col = int(e.cell[0]), int(e.cell[1])
    return msg


class GoalServer:
    """ROS goal inputs for `run` (a FleetRun guarded by `lock`). Every accepted request sets
    `request_signal`, on which an idle fleet's tick thread waits."""

    def __init__(self, owner: Node, run, lock, geometry, num_robots: int | None = None,
                 robot_actions: bool = True):
        self.run = run  # None until `bind` (the aggregator builds its run from the first poses)
        self.lock = lock
        self.geometry = geometry
        self.request_signal = self.on_request = RequestSignal()
        self._submitted = 0  # tasks submitted over fleet/submit_tasks (their default ids)
        self.episode = int(getattr(owner, "episode", 0))
        self.node = Node("mapf_goals", context=owner.context)
        n = run.num_robots if num_robots is None else int(num_robots)
        self.events_pub = self.node.create_publisher(GoalEventMsg, common.rel(GOAL_EVENTS_TOPIC),
                                                     common.reliable_qos(200))
        self._goals: dict[str, _ActionGoal] = {}  # goal id (uuid hex) -> action goal
        self._tick_seconds = 0.0  # measured mean seconds per tick (the estimated time)
        self._guard = self.node.create_guard_condition(lambda: None)  # wakes the executor
        for i in range(n):
            self.node.create_subscription(PoseStamped, common.rel(goal_pose_topic(i)),
                                          lambda msg, i=i: self._on_goal_pose(i, msg),
                                          common.reliable_qos(5))
        # one action for the whole fleet, the robot named in the goal; and, with robot_actions,
        # Nav2's per-robot name for each robot (8 DDS endpoints and a Python waitable each, which
        # every process discovers and the goal executor rebuilds per wake: docs/fleet.md)
        self.fleet_server = ActionServer(
            self.node, NavigateRobotToPose, common.rel(FLEET_NAVIGATE_ACTION),
            execute_callback=self._execute_fleet,  # a coroutine function, as below
            goal_callback=lambda req: self._on_action_goal(int(req.robot_id), req),
            cancel_callback=lambda h: self._on_cancel(int(h.request.robot_id), h))
        self.servers = [ActionServer(self.node, NavigateToPose, common.rel(navigate_action(i)),
                                     # a coroutine function (rclpy awaits it): the result
                                     # comes when the tick thread ends the goal
                                     execute_callback=functools.partial(self._execute, i),
                                     goal_callback=lambda req, i=i: self._on_action_goal(i, req),
                                     cancel_callback=lambda h, i=i: self._on_cancel(i, h))
                        for i in range(n if robot_actions else 0)]
        self.node.create_service(SubmitTasks, common.rel(SUBMIT_TASKS_SERVICE), self._on_submit)
        self.node.create_service(CancelRobotGoal, common.rel(CANCEL_GOAL_SERVICE),
                                 self._on_cancel_robot)

    def bind(self, run) -> None:
        self.run = run

    # ---- inputs (the goal executor's thread) -----------------------------------------------------
    NOT_STARTED = "the fleet has not started yet (waiting for the robots)"
    def _log_rejection(self, robot, text):
        self.node.get_logger().error(f"robot {robot}: goal rejected: {text}")

    def _on_goal_pose(self, robot: int, msg: PoseStamped):
        cell, problem = pose_goal_cell(msg, self.geometry)
        where = f"x={msg.pose.position.x!r} y={msg.pose.position.y!r}"
        if self.run is None:
            self._log_rejection(robot, f"goal_pose {where}: {self.NOT_STARTED}")
            self.publish([GoalEvent(0, robot, "rejected", cell, "goal_pose", "",
                                    self.NOT_STARTED)])
            return
        with self.lock:
            if problem:
                event = GoalEvent(self.run.tick, robot, "rejected", None, "goal_pose", "", problem)
                self.run.note([event])
            else:
                event = self.run.request_goal(robot, cell, "goal_pose",
                                              f"goal_pose-{robot}-{self.run.tick}")
        if event.event == "rejected":
            self._log_rejection(robot, f"goal_pose {where}: {event.reason}")
            self.publish([event])
        else:
            self.node.get_logger().info(f"robot {robot}: goal_pose {where} -> cell {cell}")
            self.on_request()

    def _on_action_goal(self, robot: int, request) -> GoalResponse:
        cell, problem = pose_goal_cell(request.pose, self.geometry)
        if self.run is None:
            self._log_rejection(robot, f"navigate_to_pose: {self.NOT_STARTED}")
            self.publish([GoalEvent(0, robot, "rejected", cell, "navigate_to_pose", "",
                                    self.NOT_STARTED)])
            return GoalResponse.REJECT
        with self.lock:
            problem = problem or self.run.goal_problem(robot, cell)
            event = GoalEvent(self.run.tick, robot, "rejected", cell, "navigate_to_pose", "",
                              problem)
            if problem:
                self.run.note([event])
        if problem:
            where = f"x={request.pose.pose.position.x!r} y={request.pose.pose.position.y!r}"
            self._log_rejection(robot, f"navigate_to_pose {where}: {problem}")
            self.publish([event])
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    async def _execute(self, robot: int, handle, action=NavigateToPose):
        cell, _ = pose_goal_cell(handle.request.pose, self.geometry)
        goal_id = bytes(handle.goal_id.uuid).hex()
        with self.lock:
            goal = _ActionGoal(handle, robot, cell, self.run.tick, action)
            self._goals[goal_id] = goal
            event = self.run.request_goal(robot, cell, "navigate_to_pose", goal_id)
            if event.event == "rejected":  # the fleet changed since the goal was accepted
                self._finish(goal_id, "aborted", event.reason)
        if event.event != "rejected":
            self.on_request()
        return await goal.future

    async def _execute_fleet(self, handle):
        return await self._execute(int(handle.request.robot_id), handle, NavigateRobotToPose)

    def _on_cancel(self, robot: int, handle) -> CancelResponse:
        if self.run is None:
            return CancelResponse.REJECT
        goal_id = bytes(handle.goal_id.uuid).hex()
        with self.lock:
            event = self.run.cancel(robot, goal_id, "navigate_to_pose")
        if event.event == "rejected":
            return CancelResponse.REJECT
        self.on_request()
        return CancelResponse.ACCEPT

    def _on_cancel_robot(self, request, response):
        robot = int(request.robot_id)
        if self.run is None:
            response.reason = self.NOT_STARTED
            return response
        with self.lock:
            run = self.run
            if not 0 <= robot < run.num_robots:
                response.reason = f"unknown robot {robot} (robots 0..{run.num_robots - 1})"
                return response
            if run.has_goal(robot):
                event = run.cancel(robot, "", "cancel_goal")
                response.cancelled, response.goal_id = True, event.goal_id
            else:
                response.reason = "it has no goal (it is idle)"
        if response.cancelled:
            self.node.get_logger().info(f"robot {robot}: goal {response.goal_id} cancelled")
            self.on_request()
        return response

    def _on_submit(self, request, response):
        import yaml

        if self.run is None:
            response.accepted, response.events, response.reasons = False, ["rejected"], \
                [self.NOT_STARTED]
            return response
        try:
            entries = yaml.safe_load(request.tasks)  # JSON is YAML too
            tasks = parse_tasks(entries, "submit_tasks", num_robots=self.run.num_robots,
                                cell_of=self.geometry.xy_to_cell, source="submit_tasks",
                                first_id=self._submitted)
        except (yaml.YAMLError, TaskFileError) as exc:
            from mapf_fleet.fleet.tasks import yaml_error_text

            text = (yaml_error_text("submit_tasks", exc) if isinstance(exc, yaml.YAMLError)
                    else str(exc).splitlines()[0])
            self.node.get_logger().error(f"submit_tasks rejected: {text}")
            response.accepted = False
            response.reasons = [text]
            response.events = ["rejected"]
            return response
        with self.lock:  # all or nothing: a resent request does not queue its good tasks twice
            events = self.run.submit_tasks(tasks)
        response.accepted = all(e.event == "queued" for e in events)
        if response.accepted:
            self._submitted += len(tasks)  # ids of tasks without one stay unique in the run
        for k, (t, e) in enumerate(zip(tasks, events)):
            response.task_ids.append(t.task_id)
            response.events.append(e.event)
            response.reasons.append(e.reason)
            if e.event == "rejected" and not e.reason.startswith("not queued"):
                self._log_rejection(t.robot if t.robot is not None else "any",
                                    f"submit_tasks: task {k} ({t.task_id}): {e.reason}")
        self.publish(events)  # queued / rejected; assignments follow at the tick boundary
        if response.accepted:
            self.on_request()
        return response

    # ---- from the tick thread --------------------------------------------------------------------
    def publish(self, events) -> None:
        for e in events:
            self.events_pub.publish(goal_event_msg(self.episode, e))

    def on_tick(self, events, overridden=(), tick_seconds: float | None = None) -> None:
        """After a tick (and after `apply_requests`): publish the goal events, end the action
        goals they end, and send every running action goal its feedback."""
        if tick_seconds:
            self._tick_seconds = smoothed_tick_seconds(self._tick_seconds, tick_seconds)
        self.publish(events)
        ends = {"reached": "reached", "preempted": "aborted", "aborted": "aborted",
                "cancelled": "cancelled", "rejected": "aborted"}
        finished = False
        for e in events:
            if e.goal_id in self._goals and e.event in ends:
                self._finish(e.goal_id, ends[e.event], e.reason)
                finished = True
        for goal in list(self._goals.values()):
            if goal.robot in overridden:
                goal.recoveries += 1
            self._feedback(goal)
        if finished:  # wake the goal executor for the results only: each wake rebuilds the
            self._guard.trigger()  # wait set of every robot's action server

    def _feedback(self, goal: _ActionGoal) -> None:
        run = self.run
        here = run.positions[goal.robot]
        cells = int(run.map.steps_to(goal.cell)[here[0], here[1]])  # cells, not guided costs
        fb = goal.action.Feedback()
        fb.current_pose = common.cell_pose(int(here[0]), int(here[1]), self.geometry)
        fb.distance_remaining = float(max(cells, 0) * self.geometry.resolution)
        fb.navigation_time = _duration(time.monotonic() - goal.started)
        fb.estimated_time_remaining = _duration(max(cells, 0) * self._tick_seconds)
        fb.number_of_recoveries = int(min(goal.recoveries, 32767))
        goal.handle.publish_feedback(fb)

    def _finish(self, goal_id: str, how: str, reason: str) -> None:
        goal = self._goals.pop(goal_id, None)
        if goal is None:
            return
        result = goal.action.Result()
        here = self.run.positions[goal.robot]
        result.final_pose = common.cell_pose(int(here[0]), int(here[1]), self.geometry)
        result.ticks = max(0, int(self.run.tick - goal.started_tick))
        result.reached = how == "reached"
        result.error_msg = "" if result.reached else reason
        if how == "reached":
            result.error_code = goal.action.Result.NONE
            goal.handle.succeed()
        elif how == "cancelled":
            result.error_code = goal.action.Result.CANCELED
            if goal.handle.is_cancel_requested:
                goal.handle.canceled()
            else:  # cancelled through fleet/cancel_goal: the action's own cancel was not asked
                goal.handle.abort()  # (EXECUTING -> CANCELED is no legal transition)
        else:
            result.error_code = goal.action.Result.ABORTED
            goal.handle.abort()
        goal.future.set_result(result)

    def close(self, reason: str) -> None:
        """The run ended: abort every running action goal (later requests are refused)."""
        for goal_id in list(self._goals):
            self._finish(goal_id, "aborted", reason)
        self._guard.trigger()


def smoothed_tick_seconds(mean: float, seconds: float) -> float:
    """The seconds per tick the estimated time uses, after a tick of `seconds`: a running mean
    that jumps to the new value when a tick is off it by more than half (a `param set
    tick_period`, a fleet that slowed down), so the estimate follows a new pace at once instead
    of converging over dozens of ticks."""
    if not mean or not mean / 1.5 <= seconds <= mean * 1.5:
        return float(seconds)
    return 0.8 * mean + 0.2 * seconds


def _duration(seconds: float):
    from builtin_interfaces.msg import Duration

    seconds = max(0.0, float(seconds))
    whole = int(seconds)
    return Duration(sec=whole, nanosec=int((seconds - whole) * 1e9))


class RequestSignal:
    """A flag the goal thread sets and the idle tick thread waits on."""

    def __init__(self):
        self._event = threading.Event()

    def __call__(self) -> None:
        self._event.set()

    def wait(self, timeout: float) -> bool:
        hit = self._event.wait(timeout)
        self._event.clear()
        return hit
