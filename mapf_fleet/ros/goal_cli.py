"""`mapf-fleet goal`: send a running fleet's robots somewhere (PyPI has no `ros2 action
send_goal` and no `ros2 topic pub`).

    mapf-fleet goal 3 --cell 5 7 --wait          # fleet/navigate_to_pose; feedback per tick
    mapf-fleet goal 3 --xy 5.5 7.5               # metres in the map frame; returns once accepted
    mapf-fleet goal 3 --cell 5 7 --topic         # publish on /robot_3/goal_pose (RViz's way)
    mapf-fleet goal any --cell 5 7               # the nearest idle robot (fleet/submit_tasks)
    mapf-fleet goal --tasks tasks.yaml           # many goals / pickup-dropoff tasks at once
    mapf-fleet goal 3 --cancel                   # hold robot 3 on its cell: cancels its goal
                                                 # however it was given (fleet/cancel_goal)

Exit codes: 0 accepted (with --wait: reached; --cancel: cancelled), 1 aborted or cancelled
(--wait; --cancel: the robot had no goal), 2 rejected (the reason printed, from
fleet/goal_events) or bad input, 3 no fleet answered within --timeout. A task file is queued
whole or not at all: one bad task (named by file, line and index) and none is queued.
A cell is turned into metres with the fleet's own map (`/fleet/map`: resolution and origin).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time

from mapf_fleet.ros import common

STATE_WAIT_S = 3.0  # longest wait for a fleet state before sending a robot's goal


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mapf-fleet goal", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("robot", nargs="?", help="robot id, or `any` for the nearest idle robot")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--cell", nargs=2, type=int, metavar=("ROW", "COL"),
                       help="goal cell; row 0 is the map's bottom row (docs/fleet.md, Rows and "
                            "columns)")
    where.add_argument("--xy", nargs=2, type=float, metavar=("X", "Y"),
                       help="goal in metres, map frame")
    where.add_argument("--tasks", metavar="FILE",
                       help="a task file (YAML list of goals / pickup-dropoff tasks) for "
                            "fleet/submit_tasks")
    where.add_argument("--cancel", action="store_true",
                       help="cancel the robot's goal: it holds its cell")
    p.add_argument("--wait", action="store_true",
                   help="wait for the result, printing feedback (exit 0 reached, 1 not)")
    p.add_argument("--topic", action="store_true",
                   help="publish a PoseStamped on /robot_<i>/goal_pose instead of the action "
                        "(no result to wait for)")
    p.add_argument("--namespace", default="", help="the fleet's namespace (up --namespace)")
    p.add_argument("--timeout", type=float, default=20.0,
                   help="seconds to wait for the fleet to answer (default 20; --wait: no limit "
                        "on the navigation itself)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    problem = _problem(args)
    if problem:
        print(f"mapf-fleet goal: {problem}", file=sys.stderr)
        return 2
    common.prepare_environment()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from mapf_fleet.ros.processes import stop_signals

    signals = stop_signals()
    rclpy.init(args=["mapf_goal"] + (["--ros-args", "-r", f"__ns:=/{args.namespace.strip('/')}"]
                                     if args.namespace.strip("/") else []))
    node = rclpy.create_node(f"mapf_goal_{int(time.time() * 1000) % 100000}")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = common.SpinThread(executor).start()
    try:
        client = GoalClient(node, args)
        return client.run(signals)
    finally:
        spinner.stop()
        node.destroy_node()
        rclpy.try_shutdown()
        signals.restore()


def _problem(args) -> str:
    if args.tasks:
        if args.robot is not None:
            return "--tasks names its robots in the file: give no ROBOT"
        return ""
    if args.robot is None:
        return "give a ROBOT id (or `any`) and --cell ROW COL / --xy X Y, or --tasks FILE"
    if args.robot != "any":
        try:
            if int(args.robot) < 0:
                raise ValueError
        except ValueError:
            return f"ROBOT must be a robot id (0, 1, ...) or `any`, got {args.robot!r}"
    if args.cancel:
        if args.robot == "any" or args.topic:
            return "--cancel needs one robot id and the action (no --topic)"
        return ""
    if args.cell is None and args.xy is None:
        return "give the goal: --cell ROW COL or --xy X Y"
    if args.robot == "any" and (args.topic or args.wait):
        return "`any` goes through fleet/submit_tasks: no --topic, no --wait"
    if args.topic and args.wait:
        return "--topic has no result to --wait for (use the action: drop --topic)"
    return ""


class GoalClient:
    def __init__(self, node, args):
        from mapf_fleet_interfaces.msg import GoalEvent
        from nav_msgs.msg import OccupancyGrid

        self.node = node
        self.args = args
        # --timeout bounds the whole command, not each of its waits (they used to add up)
        self.deadline = time.monotonic() + args.timeout
        self.map_msg = None
        self.events: list = []
        self.cond = threading.Condition()
        node.create_subscription(OccupancyGrid, common.rel(common.MAP_TOPIC), self._on_map,
                                 common.latched_qos())
        from mapf_fleet.ros.goals import GOAL_EVENTS_TOPIC

        self.events_sub = node.create_subscription(GoalEvent, common.rel(GOAL_EVENTS_TOPIC),
                                                   self._on_event, common.reliable_qos(200))
        from mapf_fleet_interfaces.msg import FleetState

        self.robots = None  # how many robots the fleet state names (None: no state heard)
        node.create_subscription(FleetState, common.rel(common.STATE_TOPIC), self._on_state,
                                 common.reliable_qos(10))

    def _on_state(self, msg):
        with self.cond:
            self.robots = len(msg.rows)
            self.cond.notify_all()

    def _on_map(self, msg):
        with self.cond:
            self.map_msg = msg
            self.cond.notify_all()

    def _on_event(self, msg):
        with self.cond:
            self.events.append(msg)
            self.cond.notify_all()

    def left(self) -> float:
        """Seconds left of --timeout."""
        return max(0.0, self.deadline - time.monotonic())

    def _wait(self, predicate, timeout: float, signals) -> bool:
        deadline = time.monotonic() + timeout
        with self.cond:
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0 or signals.requested:
                    return False
                self.cond.wait(min(left, 0.2))
        return True

    def _pose(self, signals):
        from geometry_msgs.msg import PoseStamped

        msg = PoseStamped()
        msg.header.frame_id = common.FRAME_ID
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.pose.orientation.w = 1.0
        if self.args.xy is not None:
            msg.pose.position.x, msg.pose.position.y = self.args.xy
            return msg
        if not self._wait(lambda: self.map_msg is not None, self.left(), signals):
            return None
        _, geometry = common.occupancy_to_grid(self.map_msg)
        msg.pose.position.x, msg.pose.position.y = geometry.cell_to_xy(*self.args.cell)
        return msg

    def _rejection(self, robot: int, since: int, signals) -> str:
        """The reason of the fleet's last rejection for `robot` (from goal events)."""
        found = lambda: [e for e in self.events[since:]  # noqa: E731
                         if e.event == "rejected" and e.robot_id == robot]
        self._wait(lambda: bool(found()), 3.0, signals)
        hits = found()
        return hits[-1].reason if hits else "(no reason received on fleet/goal_events)"

    def run(self, signals) -> int:
        args = self.args
        # goal events are volatile: hear the fleet's publisher first, so a rejection's reason
        # is not missed (a fleet without goal events still gets the goal)
        _wait_for(lambda: self.events_sub.get_publisher_count() > 0, min(self.left(), 5.0),
                  signals)
        if args.tasks:
            return self._submit_file(args.tasks, signals)
        if args.robot == "any":
            pose = self._pose(signals) if args.cell is None else None
            goal = ({"goal": list(args.cell)} if args.cell is not None
                    else {"xy": [pose.pose.position.x, pose.pose.position.y]})
            import json

            return self._submit(json.dumps([goal]), signals)
        robot = int(args.robot)
        if args.cancel:  # the fleet checks the robot id itself, at once
            return self._cancel(robot, signals)
        # the fleet's state names its robots (a tick, or every few seconds when idle): an id
        # past them is refused at once instead of after --timeout
        self._wait(lambda: self.robots is not None, min(self.left(), STATE_WAIT_S), signals)
        if self.robots is not None and robot >= self.robots:
            print(f"mapf-fleet goal: robot {robot}: the fleet has {self.robots} robots "
                  f"(0..{self.robots - 1})", file=sys.stderr)
            return 2
        pose = self._pose(signals)
        if pose is None:
            print(f"mapf-fleet goal: no fleet map on {common.MAP_TOPIC} within {args.timeout} s "
                  f"(is the fleet up, in this namespace?)", file=sys.stderr)
            return 3
        where = f"x={pose.pose.position.x:.3f} y={pose.pose.position.y:.3f}"
        if args.topic:
            return self._publish(robot, pose, where, signals)
        return self._navigate(robot, pose, where, signals)

    def _publish(self, robot, pose, where, signals) -> int:
        from geometry_msgs.msg import PoseStamped

        from mapf_fleet.ros.goals import goal_pose_topic

        pub = self.node.create_publisher(PoseStamped, common.rel(goal_pose_topic(robot)),
                                         common.reliable_qos(5))
        if not _wait_for(lambda: pub.get_subscription_count() > 0, self.left(), signals):
            print(f"mapf-fleet goal: nobody subscribes to {goal_pose_topic(robot)} within "
                  f"{self.args.timeout} s", file=sys.stderr)
            return 3
        since = len(self.events)
        pub.publish(pose)
        # the fleet answers every goal with an event: assigned-on-accept comes at the next tick,
        # a rejection at once
        if self._wait(lambda: any(e.robot_id == robot and e.event == "rejected"
                                  for e in self.events[since:]), 1.5, signals):
            print(f"robot {robot}: goal {where} rejected: {self._rejection(robot, since, signals)}")
            return 2
        print(f"robot {robot}: goal {where} published on {goal_pose_topic(robot)}")
        return 0

    def _navigate(self, robot, pose, where, signals) -> int:
        # the fleet's own action (the robot named in the goal): served whatever the fleet's size,
        # one server to discover (large fleets leave out the per-robot ones: robot_actions)
        from mapf_fleet_interfaces.action import NavigateRobotToPose
        from rclpy.action import ActionClient

        from mapf_fleet.ros.goals import FLEET_NAVIGATE_ACTION

        client = ActionClient(self.node, NavigateRobotToPose, common.rel(FLEET_NAVIGATE_ACTION))
        if not client.wait_for_server(timeout_sec=self.left()):
            print(f"mapf-fleet goal: no action server {FLEET_NAVIGATE_ACTION} within "
                  f"{self.args.timeout} s (is the fleet up, in this namespace?)", file=sys.stderr)
            return 3
        since = len(self.events)

        def feedback(msg):
            fb = msg.feedback
            p = fb.current_pose.pose.position
            print(f"robot {robot}: at x={p.x:.2f} y={p.y:.2f}, {fb.distance_remaining:.2f} m "
                  f"to go, about {fb.estimated_time_remaining.sec + fb.estimated_time_remaining.nanosec * 1e-9:.1f} s, "
                  f"{fb.number_of_recoveries} overridden moves", flush=True)

        # a reply can be lost while the server has not matched this client's reply reader yet
        # (discovery on a loaded machine): ask again; a goal sent twice preempts its twin
        sent = _ask(lambda: client.send_goal_async(
            NavigateRobotToPose.Goal(robot_id=robot, pose=pose),
            feedback_callback=feedback if self.args.wait else None), self.left(), signals)
        if sent is None:
            print(f"mapf-fleet goal: the goal was not answered within {self.args.timeout:g} s",
                  file=sys.stderr)
            return 3
        handle = sent.result()
        if not handle.accepted:
            print(f"robot {robot}: goal {where} rejected: {self._rejection(robot, since, signals)}")
            return 2
        print(f"robot {robot}: goal {where} accepted", flush=True)
        if not self.args.wait:
            return 0
        result = handle.get_result_async()
        while not _wait_for(result.done, 1.0, signals):
            if signals.requested:
                handle.cancel_goal_async()
                _wait_for(result.done, 5.0, None)
                print(f"robot {robot}: cancelled (Ctrl-C)")
                return signals.exit_code
        res = result.result().result
        if res.reached:
            print(f"robot {robot}: reached {where} after {res.ticks} ticks")
            return 0
        print(f"robot {robot}: not reached ({'cancelled' if res.error_code == 2 else 'aborted'}): "
              f"{res.error_msg}")
        return 1

    def _cancel(self, robot, signals) -> int:
        # the fleet's own service, whatever gave the goal (fleet or per-robot action, goal_pose,
        # a task, the task source) and whatever the fleet's size (no per-robot server needed)
        from mapf_fleet_interfaces.srv import CancelRobotGoal

        from mapf_fleet.ros.goals import CANCEL_GOAL_SERVICE

        client = self.node.create_client(CancelRobotGoal, common.rel(CANCEL_GOAL_SERVICE))
        if not client.wait_for_service(timeout_sec=self.left()):
            print(f"mapf-fleet goal: no service {CANCEL_GOAL_SERVICE} within "
                  f"{self.args.timeout:g} s (is the fleet up, in this namespace?)",
                  file=sys.stderr)
            return 3
        # a cancel asked twice is harmless: the second finds the robot idle, so only the first
        # answer counts and a lost reply is asked again
        future = _ask(lambda: client.call_async(CancelRobotGoal.Request(robot_id=robot)),
                      self.left(), signals)
        if future is None:
            print(f"mapf-fleet goal: {CANCEL_GOAL_SERVICE} did not answer within "
                  f"{self.args.timeout:g} s", file=sys.stderr)
            return 3
        res = future.result()
        if res.cancelled:
            print(f"robot {robot}: goal {res.goal_id} cancelled: it holds its cell")
            return 0
        print(f"robot {robot}: nothing to cancel: {res.reason}")
        return 1 if "no goal" in res.reason else 2

    def _submit_file(self, path: str, signals) -> int:
        """A task file: checked here first (YAML, fields: errors name the file, its line and the
        task's index), then sent whole; the fleet's rejections are named the same way."""
        from mapf_fleet.fleet.tasks import TaskFileError, entry_lines, load_task_file

        try:
            load_task_file(path, cell_of=lambda x, y: (0, 0))  # its form; metres: the fleet's map
            text = open(path, encoding="utf-8").read()
        except (TaskFileError, OSError, UnicodeDecodeError) as exc:
            print(f"mapf-fleet goal: {exc}", file=sys.stderr)
            return 2
        lines = entry_lines(text)
        return self._submit(text, signals, lambda k: f"{path}:{lines[k]}: task {k}"
                            if k < len(lines) else f"{path}: task {k}")

    def _submit(self, text: str, signals, name=lambda k: f"task {k}") -> int:
        from mapf_fleet_interfaces.srv import SubmitTasks

        from mapf_fleet.ros.goals import SUBMIT_TASKS_SERVICE

        client = self.node.create_client(SubmitTasks, common.rel(SUBMIT_TASKS_SERVICE))
        if not client.wait_for_service(timeout_sec=self.left()):
            print(f"mapf-fleet goal: no service {SUBMIT_TASKS_SERVICE} within "
                  f"{self.args.timeout} s (is the fleet up?)", file=sys.stderr)
            return 3
        since = len(self.events)
        # a lost reply is asked again unless the fleet's goal events show the tasks arrived
        # (a second request would queue them twice)
        arrived = lambda: any(e.source == "submit_tasks" for e in self.events[since:])  # noqa
        future = _ask(lambda: client.call_async(SubmitTasks.Request(tasks=text)),
                      self.left(), signals, stop=arrived)
        if future is None and arrived():
            with self.cond:
                seen = [e for e in self.events[since:] if e.source == "submit_tasks"]
            for e in seen:
                print(f"task {e.goal_id}: {e.event}" + (f": {e.reason}" if e.reason else ""))
            return 2 if any(e.event == "rejected" for e in seen) else 0
        if future is None:
            print(f"mapf-fleet goal: {SUBMIT_TASKS_SERVICE} did not answer within "
                  f"{self.args.timeout:g} s", file=sys.stderr)
            return 3
        res = future.result()
        if not res.accepted:  # all or nothing: the bad tasks with their reasons, nothing queued
            for k, reason in enumerate(res.reasons):
                if res.events[k] == "rejected" and not reason.startswith("not queued"):
                    print(f"{name(k)}" + (f" ({res.task_ids[k]})" if k < len(res.task_ids)
                                          else "") + f": rejected: {reason}", file=sys.stderr)
            if len(res.events) > 1:
                print(f"mapf-fleet goal: nothing queued ({len(res.events)} tasks sent, queued "
                      f"whole or not at all): fix the task named and send again",
                      file=sys.stderr)
            return 2
        queued = []
        for k, event in enumerate(res.events):
            ident = res.task_ids[k] if k < len(res.task_ids) else str(k)
            print(f"{name(k)} ({ident}): {event}", flush=True)
            queued.append(ident)
        if queued and self.args.robot == "any":  # say which robot took it (next tick or two)
            taken = lambda: [e for e in self.events[since:]  # noqa: E731
                             if e.event == "assigned" and e.goal_id.split("/")[0] in queued]
            self._wait(lambda: bool(taken()), 3.0, signals)
            for e in taken():
                print(f"task {e.goal_id.split('/')[0]}: assigned to robot {e.robot_id}")
        return 0


def _ask(send, timeout: float, signals, stop=lambda: False, attempts: int = 4):
    """`send()` (a request; returns its future) until it is answered: asked again after
    timeout / attempts seconds without an answer, unless `stop()`; the answered future, or None
    when none came within `timeout`."""
    per_try = max(timeout / attempts, 1.0)
    deadline = time.monotonic() + timeout
    while True:
        future = send()
        left = deadline - time.monotonic()
        if _wait_for(future.done, min(per_try, max(left, 0.0)), signals):
            return future
        if time.monotonic() >= deadline or (signals is not None and signals.requested) \
                or stop():
            return None


def _wait_for(predicate, timeout: float, signals) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline or (signals is not None and signals.requested):
            return False
        time.sleep(0.05)
    return True


if __name__ == "__main__":
    sys.exit(main())
