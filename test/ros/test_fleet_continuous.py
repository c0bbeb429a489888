"""A fleet that runs continuously: a lifelong fleet over ROS equals the evaluator's
lifelong rollout on the same core; goals at run time from a plain rclpy `goal_pose` publisher,
the `navigate_to_pose` action (feedback, result, preempt, cancel, rejection with the reason) and
the task service, in the simulator and with stand-in robots (real-robot mode)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from mapf_fleet.coordination.rules import FLEET_RULE
from mapf_fleet.fleet.instances import InstanceSource

UP = [sys.executable, "-m", "mapf_fleet.cli", "up", "--quiet"]
# every process these tests start gets `ros_env` (test/conftest.py): its own ROS_DOMAIN_ID and
# ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, so nothing leaves loopback


RULE = FLEET_RULE  # the fleet's default conflict rule, named on both sides


def _first_difference(got, want):
    """The first tick where two per-tick lists differ, with both sides (None if equal): pytest's
    own diff of 200 ticks x 16 cells takes tens of minutes on a failing run."""
    for tick, (a, b) in enumerate(zip(got, want)):
        if a != b:
            return f"tick {tick}: {a} != {b}"
    return None if len(got) == len(want) else f"{len(got)} ticks != {len(want)}"


def _lifelong_rollout(checkpoint, instance, steps, seed, guidance):
    import torch

    from mapf_fleet.evaluation.lifelong import rollout
    from mapf_fleet.evaluation.policies import CheckpointBatchPolicy
    from mapf_fleet.fleet.run import FleetRun
    from mapf_fleet.fleet.tasks import LifelongTasks
    from mapf_fleet.grid.guidance_made import GuidanceSource

    torch.set_num_threads(1)
    source = GuidanceSource.parse(guidance)
    run = FleetRun(instance.grid, instance.starts, LifelongTasks(grid=instance.grid, seed=seed),
                   instance.goals, rule=RULE, max_steps=steps,
                   guidance=source.for_map(instance.grid), flow=source.flow(instance.grid))
    rollout(CheckpointBatchPolicy(checkpoint, ranking="q"), [run], shielded=True)
    return run


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("algo,guidance", [
    ("dhc", "none"), ("dcc_sensitive", None), ("dcc_sensitive", "congestion"),
    ("dcc_sensitive", "models/guidance/online_epibt_warehouse_33x33_128.online.json")])
def test_lifelong_fleet_equals_the_evaluators_lifelong_rollout(tmp_path, ros_env, checkpoints,
                                                               algo, guidance):
    """16 robots, 200 ticks, two policy processes of 8: every cell of every tick and every goal
    change equal `evaluate --lifelong`'s rollout (`evaluation.lifelong.rollout` over the same
    `FleetRun`), goal stream seeded alike; unguided (`--guidance none`) and under `up`'s default
    guidance (None: no --guidance, the fleet's `FLEET_GUIDANCE`: every node's distances, the
    robots' heuristic channels and the rule read the same graph as the rollout's), and under
    online guidance (congestion: the policy processes follow the graph from the states)."""
    from mapf_fleet.coordination.rules import FLEET_GUIDANCE

    if guidance and guidance.endswith(".json"):  # a shipped model, wherever pytest runs
        guidance = str(Path(__file__).resolve().parents[2] / guidance)
    seed, steps = 5, 200
    instance = InstanceSource(num_robots=16, size=16, density=0.2, seed=seed).load()
    expected = _lifelong_rollout(checkpoints[algo], instance, steps, seed,
                                 FLEET_GUIDANCE if guidance is None else guidance)
    assigned = [e for e in expected.recorder.record["goal_events"] if e["event"] == "assigned"]
    assert len(assigned) > 16 + 4  # robots really got new goals on arrival
    record_path = tmp_path / "lifelong.json"
    proc = subprocess.run(UP + ["--checkpoint", checkpoints[algo], "--num-robots", "16",
                                "--size", "16", "--density", "0.2", "--seed", str(seed),
                                "--task-source", "lifelong", "--max-steps", str(steps),
                                "--nodes-per-process", "8", "--ranking", "q",
                                "--conflict-rule", RULE,
                                *([] if guidance is None else ["--guidance", guidance]),
                                "--record", str(record_path)],
                          env=ros_env, capture_output=True, text=True, timeout=900)
    assert record_path.exists(), proc.stdout + proc.stderr
    record = json.loads(record_path.read_text())
    want = expected.recorder.record
    assert record["missed_decisions"] == 0, record["summary"]
    assert _first_difference(record["positions"], want["positions"]) is None, record["summary"]
    assert _first_difference(record["goal_events"], want["goal_events"]) is None
    assert record["goals_reached"] == expected.goals_reached
    assert "throughput" in record["summary"] and proc.returncode == 0, proc.stdout + proc.stderr


class FleetClient:
    """An rclpy client of a running fleet in this test process: goal_pose publishers, the
    navigate_to_pose action (each robot's, or with `fleet_action` the fleet's, the robot in the
    goal), goal events."""

    def __init__(self, num_robots, fleet_action=False):
        import rclpy
        from geometry_msgs.msg import PoseStamped
        from mapf_fleet_interfaces.action import NavigateRobotToPose, NavigateToPose
        from mapf_fleet_interfaces.msg import FleetState, GoalEvent
        from rclpy.action import ActionClient
        from rclpy.executors import SingleThreadedExecutor

        from mapf_fleet.ros import common

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("continuous_test_client", context=self.context)
        self.events, self.states = [], []
        self.lock = threading.Lock()
        self.events_sub = self.node.create_subscription(
            GoalEvent, "fleet/goal_events", lambda m: self._add(self.events, m),
            common.reliable_qos(500))
        self.node.create_subscription(FleetState, "fleet/state",
                                      lambda m: self._add(self.states, m), common.reliable_qos(50))
        self.goal_pubs = [self.node.create_publisher(PoseStamped, f"robot_{i}/goal_pose",
                                                     common.reliable_qos(5))
                          for i in range(num_robots)]
        self.fleet_action = fleet_action
        if fleet_action:
            fleet = ActionClient(self.node, NavigateRobotToPose, "fleet/navigate_to_pose")
            self.actions = [fleet] * num_robots
        else:
            self.actions = [ActionClient(self.node, NavigateToPose,
                                         f"robot_{i}/navigate_to_pose")
                            for i in range(num_robots)]
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.spinner = common.SpinThread(self.executor).start()

    def _add(self, items, msg):
        with self.lock:
            items.append(msg)

    def close(self):
        import rclpy

        self.spinner.stop()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    def pose(self, row, col, frame="map"):
        from geometry_msgs.msg import PoseStamped

        msg = PoseStamped()
        msg.header.frame_id = frame
        msg.pose.position.x, msg.pose.position.y = col + 0.5, row + 0.5  # resolution 1, origin 0
        msg.pose.orientation.w = 1.0
        return msg

    def wait(self, predicate, timeout=120.0, what=""):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                if predicate():
                    return
            time.sleep(0.05)
        raise AssertionError(f"timed out waiting for {what}")

    def event(self, robot, kind):
        return [e for e in self.events if e.robot_id == robot and e.event == kind]

    def send(self, robot, row, col, feedback=None):
        from mapf_fleet_interfaces.action import NavigateRobotToPose, NavigateToPose

        assert self.actions[robot].wait_for_server(timeout_sec=60.0)
        goal = (NavigateRobotToPose.Goal(robot_id=robot, pose=self.pose(row, col))
                if self.fleet_action else NavigateToPose.Goal(pose=self.pose(row, col)))
        # a service response can be lost while the server has not matched the client's reply
        # reader yet (discovery on a loaded machine): ask again, as a user would
        for attempt in range(3):
            future = self.actions[robot].send_goal_async(goal, feedback_callback=feedback)
            try:
                self.wait(future.done, 30.0, "the goal response")
                return future.result()
            except AssertionError:
                if attempt == 2:
                    raise


def _far_free_cells(instance, count):
    """Free cells of the instance's region far from every start (goal candidates)."""
    from mapf_fleet.grid.heuristic import bfs_distances

    starts = {tuple(s) for s in np.asarray(instance.starts).tolist()}
    dist = bfs_distances(instance.grid, tuple(instance.starts[0]))
    cells = [tuple(map(int, c)) for c in np.argwhere(dist >= 0)
             if tuple(map(int, c)) not in starts]
    cells.sort(key=lambda c: -int(dist[c]))
    return cells[:count]


def _far_from(instance, cell, count):
    from mapf_fleet.grid.heuristic import bfs_distances

    dist = bfs_distances(instance.grid, cell)
    order = np.argsort(-dist.ravel(), kind="stable")
    return [divmod(int(k), dist.shape[1]) for k in order[:count]]


def _start_fleet(tmp_path, ros_env, checkpoint, extra, name):
    record = tmp_path / f"{name}.json"
    log = open(tmp_path / f"{name}.log", "w")
    proc = subprocess.Popen(UP + ["--checkpoint", checkpoint, "--record", str(record),
                                  "--task-source", "external", *extra],
                            env=ros_env, stdout=log, stderr=subprocess.STDOUT, text=True)
    return proc, record, tmp_path / f"{name}.log"


def _exercise_goals(client, instance, robots):
    """goal_pose (plain publisher), the action (feedback decreasing, reached), preempt, cancel
    and a rejection with its reason."""
    # goal events are volatile: hear the fleet's publisher before anything is sent, and wait
    # for the fleet's first state (real robots: once every robot has posed)
    client.wait(lambda: client.events_sub.get_publisher_count() > 0, 60, "fleet/goal_events")
    client.wait(lambda: client.states, 120, "the fleet's first state")
    a, b, c, d = _far_free_cells(instance, 4)
    r0, r1 = robots
    # a goal on an obstacle: rejected, the reason on fleet/goal_events
    wall = tuple(map(int, np.argwhere(np.asarray(instance.grid) != 0)[0]))
    handle = client.send(r1, *wall)
    assert not handle.accepted
    client.wait(lambda: client.event(r1, "rejected"), 30, "the rejection event")
    assert "obstacle" in client.event(r1, "rejected")[-1].reason
    # a plain rclpy publisher on /robot_<r0>/goal_pose
    client.wait(lambda: client.goal_pubs[r0].get_subscription_count() > 0, 60, "goal_pose sub")
    client.goal_pubs[r0].publish(client.pose(*a))
    client.wait(lambda: client.event(r0, "reached"), 240, f"robot {r0} reaching {a}")
    assert (client.event(r0, "reached")[-1].row, client.event(r0, "reached")[-1].col) == a
    # the action: feedback every tick, distance going down, result reached
    distances = []
    handle = client.send(r1, *b, feedback=lambda m: distances.append(m.feedback.distance_remaining))
    assert handle.accepted
    result = handle.get_result_async()
    client.wait(result.done, 240, f"robot {r1} reaching {b}")
    assert result.result().result.reached and result.result().result.error_msg == ""
    assert len(distances) >= 2 and distances[-1] < distances[0] and min(distances) <= 1.0
    # preempt: a second goal ends the first one aborted, naming the new goal (both far from b)
    c, d = _far_from(instance, b, 2)
    first = client.send(r1, *c)
    assert first.accepted
    first_result = first.get_result_async()
    client.wait(lambda: [e for e in client.events if e.robot_id == r1 and e.event == "assigned"
                         and (e.row, e.col) == c], 30, "the first goal assigned")
    second = client.send(r1, *d)
    client.wait(first_result.done, 60, "the preempted result")
    res = first_result.result().result
    assert not res.reached and "preempted" in res.error_msg
    # cancel the second: the robot holds its cell
    cancel = second.cancel_goal_async()
    client.wait(cancel.done, 30, "the cancel response")
    second_result = second.get_result_async()
    client.wait(second_result.done, 60, "the cancelled result")
    assert second_result.result().result.error_code == 2  # CANCELED
    client.wait(lambda: client.event(r1, "cancelled"), 30, "the cancelled event")


def _exercise_then_stop(proc, record_path, log, instance, robots, stop=(), fleet_action=False):
    """`_exercise_goals` on the running fleet `proc`, then Ctrl-C (and `stop`'s processes):
    the fleet exits 130; its record."""
    client = FleetClient(len(instance.starts), fleet_action)
    try:
        _exercise_goals(client, instance, robots)
        if fleet_action:  # a goal for no robot is refused with the reason
            from mapf_fleet_interfaces.action import NavigateRobotToPose

            unknown = len(instance.starts)
            future = client.actions[0].send_goal_async(
                NavigateRobotToPose.Goal(robot_id=unknown, pose=client.pose(*robots)))
            client.wait(future.done, 30, "the unknown robot's goal response")
            assert not future.result().accepted
            client.wait(lambda: client.event(unknown, "rejected"), 30, "its rejection event")
            assert "unknown robot" in client.event(unknown, "rejected")[-1].reason
    finally:
        client.close()
        proc.send_signal(signal.SIGINT)
        code = proc.wait(120)
        for other in stop:
            other.send_signal(signal.SIGINT)
            other.wait(60)
    assert code == 130, log.read_text()[-3000:]
    return json.loads(record_path.read_text())


@pytest.mark.ros
@pytest.mark.slow
def test_simulated_fleet_takes_goals_at_run_time(tmp_path, ros_env, checkpoints):
    seed = 3
    instance = InstanceSource(num_robots=4, size=12, density=0.2, seed=seed).load()
    # ticks of at least 0.2 s, as robots would take: free-running, the robot preempted towards d
    # reached it in 9 ticks (about 0.3 s) before a loaded machine's cancel got there, so the
    # cancel met a finished goal (CI, session 13); the real-robot test is paced by its stand-ins
    proc, record_path, log = _start_fleet(
        tmp_path, ros_env, checkpoints["dcc"],
        ["--num-robots", "4", "--size", "12", "--density", "0.2", "--seed", str(seed),
         "--nodes-per-process", "2", "--ros-args", "-p", "mapf_simulator:tick_period:=0.2"], "sim")
    record = _exercise_then_stop(proc, record_path, log, instance, (0, 1))
    kinds = {e["event"] for e in record["goal_events"]}
    assert {"assigned", "reached", "preempted", "cancelled", "rejected"} <= kinds
    assert record["summary"].startswith("stopped at tick")


@pytest.mark.ros
@pytest.mark.slow
def test_real_robot_mode_takes_goals_at_run_time_and_robots_never_share_a_cell(
        tmp_path, ros_env, checkpoints):
    from mapf_fleet.fleet.instances import dump_instance_yaml

    instance = InstanceSource(num_robots=4, size=12, density=0.2, seed=3).load()
    path = tmp_path / "instance.yaml"
    dump_instance_yaml(instance, path)
    stand_ins = subprocess.Popen([sys.executable, "-m", "mapf_fleet.ros.stand_in_robot",
                                  "--instance", str(path), "--max-delay", "0.2"],
                                 env=ros_env, stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL)
    proc, record_path, log = _start_fleet(
        tmp_path, ros_env, checkpoints["dcc"],
        ["--instance", str(path), "--real-robots", "--nodes-per-process", "2",
         "--ros-args", "-p", "robot_actions:=false"], "real")
    record = _exercise_then_stop(proc, record_path, log, instance, (2, 3), stop=[stand_ins],
                                 fleet_action=True)
    assert record["goal_events"] and record["steps"] > 0
    for tick, cells in enumerate(record["positions"]):
        assert len({tuple(c) for c in cells}) == len(cells), f"two robots in one cell at {tick}"


@pytest.mark.ros
def test_robot_actions_false_serves_only_the_fleets_action(ros_env):
    """The node's own servers (the ROS graph of a domain can still list a stopped fleet's
    endpoints for a while, so the test asks the node, not the graph)."""
    import rclpy
    from rclpy.parameter import Parameter

    from mapf_fleet.ros.simulator_node import SimulatorNode

    rclpy.init(args=["test"])
    try:
        for robot_actions, servers in ((False, 0), (True, 3)):
            sim = SimulatorNode(parameter_overrides=[
                Parameter("num_robots", value=3), Parameter("task_source", value="external"),
                Parameter("max_steps", value=0), Parameter("robot_actions", value=robot_actions)])
            assert len(sim.goals.servers) == servers
            assert sim.goals.fleet_server is not None
            sim.goals.node.destroy_node()
            sim.destroy_node()
    finally:
        rclpy.try_shutdown()


@pytest.mark.ros
def test_a_building_map_yaml_sets_the_fleet_map_its_resolution_and_origin(tmp_path, ros_env):
    """`map_file: F.yaml` (Nav2 map_server) in the simulator: the grid downsampled to
    `cell_size`, /fleet/map with that resolution and the map's origin, poses in its metres."""
    import rclpy
    from nav_msgs.msg import OccupancyGrid
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from mapf_fleet.grid.nav2_map import read_nav2_map, write_nav2_map
    from mapf_fleet.ros import common
    from mapf_fleet.ros.simulator_node import SimulatorNode

    grid = np.zeros((12, 16), dtype=np.int8)
    grid[4, 2:12] = 1
    grid[9, 6] = -1  # unknown: blocked
    path = tmp_path / "building.yaml"
    write_nav2_map(path, grid, 0.05, origin=(-2.0, 3.0, 0.0))
    expected = read_nav2_map(path, 0.1)
    assert expected.grid.shape == (6, 8) and expected.grid[2, 1:6].all() and expected.grid[4, 3]
    rclpy.init(args=["test"])
    try:
        sim = SimulatorNode(parameter_overrides=[
            Parameter("map_file", value=str(path)), Parameter("cell_size", value=0.1),
            Parameter("num_robots", value=3), Parameter("task_source", value="external"),
            Parameter("max_steps", value=0)])
        listener = rclpy.create_node("map_listener")
        maps = []
        listener.create_subscription(OccupancyGrid, "fleet/map", maps.append,
                                     common.latched_qos())
        executor = SingleThreadedExecutor()
        executor.add_node(listener)
        executor.add_node(sim)
        deadline = time.monotonic() + 30
        while not maps and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        assert maps, "no /fleet/map"
        info = maps[0].info
        assert (info.height, info.width) == (6, 8)
        assert info.resolution == pytest.approx(0.1)
        assert (info.origin.position.x, info.origin.position.y) == pytest.approx((-2.0, 3.0))
        got = (np.asarray(maps[0].data).reshape(6, 8) == 100)
        assert (got == (expected.grid != 0)).all()
        # robots start on free cells of that map, their poses in its metres
        for r, c in sim.run.positions:
            assert not expected.grid[r, c]
            assert sim.geometry.xy_to_cell(*expected.cell_to_xy(r, c)) == (r, c)
        sim.destroy_node()
        listener.destroy_node()
    finally:
        rclpy.try_shutdown()
