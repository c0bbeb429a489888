"""`mapf-fleet goal` against the fleet's goal server (ros/goals.py) in this process, on a fleet
core that ticks without robots moving (issue 40, items 2, 4, 6, 8):

- `goal R --cancel` cancels a goal however it was given (here through the fleet's action, as
  `goal R --cell` sends it) with per-robot actions off (the 256+ robot layout), in seconds, and
  says so when there is nothing to cancel; a client waiting on that goal ends "cancelled";
- `goal --tasks F` is all or nothing: one bad task and none is queued, the bad one named by file,
  line and index; sent again after the fix, each task is queued once; a YAML syntax error names
  file and line;
- `goal any` during an instance run is refused at once with the reason;
- the feedback's time estimate follows a new tick period within a tick or two."""

# Loopback only: every ROS process these tests start runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
# and its own ROS_DOMAIN_ID (test/conftest.py, ros_env / _isolate_ros_tests).

from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import pytest

GOAL = [sys.executable, "-m", "mapf_fleet.cli", "goal"]
GRID = np.zeros((8, 8), dtype=np.uint8)
GRID[4, 4] = 1  # an obstacle
STARTS = np.array([[0, 0], [7, 7], [0, 7]])


class Fleet:
    """A FleetRun behind a GoalServer, its map latched on /fleet/map, ticked every 0.1 s (goal
    requests applied, events published; the robots stay where they are)."""

    def __init__(self, source="external"):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        from mapf_fleet.fleet.run import FleetRun
        from mapf_fleet.fleet.tasks import ExternalTasks, InstanceTasks
        from mapf_fleet.fleet.topics import MapGeometry
        from mapf_fleet.ros import common
        from mapf_fleet.ros.goals import GoalServer

        tasks = ExternalTasks() if source == "external" else InstanceTasks()
        goals = None if source == "external" else np.array([[1, 1], [6, 6], [1, 6]])
        self.run = FleetRun(GRID, STARTS, tasks, goals, rule="pibt",
                            max_steps=0 if source == "external" else 500)
        self.lock = threading.Lock()
        self.owner = rclpy.create_node("fake_simulator")
        geometry = MapGeometry()
        pub = self.owner.create_publisher(type(common.grid_to_occupancy(GRID, geometry)),
                                          common.MAP_TOPIC, common.latched_qos())
        pub.publish(common.grid_to_occupancy(GRID, geometry))
        self.goals = GoalServer(self.owner, self.run, self.lock, geometry, robot_actions=False)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.owner)
        self.executor.add_node(self.goals.node)
        self.spinner = common.SpinThread(self.executor).start()
        self.stop = threading.Event()
        self.ticker = threading.Thread(target=self._tick, daemon=True)
        self.ticker.start()

    def _tick(self):
        while not self.stop.wait(0.1):
            with self.lock:
                events = self.run.apply_requests()
            self.goals.on_tick(events, tick_seconds=0.1)

    def events(self, kind):
        return [e for e in self.run.recorder.record["goal_events"] if e["event"] == kind]

    def close(self):
        self.stop.set()
        self.ticker.join(5)
        self.spinner.stop()
        self.goals.node.destroy_node()
        self.owner.destroy_node()


@pytest.fixture
def fleet(rclpy_context):
    made = []
    yield lambda source="external": made.append(Fleet(source)) or made[-1]
    for f in made:
        f.close()


def goal(ros_env, *args, timeout=60):
    return subprocess.run(GOAL + [str(a) for a in args], env=ros_env, capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.ros
def test_cancel_stops_a_goal_from_the_fleets_action_without_per_robot_actions(ros_env, fleet):
    f = fleet()
    assert f.goals.servers == []  # the 256+ robot layout: no robot_<i>/navigate_to_pose
    waiter = subprocess.Popen(GOAL + ["1", "--cell", "7", "0", "--wait", "--timeout", "30"],
                              env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True)
    try:
        deadline = time.monotonic() + 60
        while not f.events("assigned") and time.monotonic() < deadline:
            time.sleep(0.1)
        assert f.events("assigned") and f.run.active[1]
        started = time.monotonic()
        done = goal(ros_env, 1, "--cancel", "--timeout", "8")
        took = time.monotonic() - started
        assert done.returncode == 0, done.stdout + done.stderr
        assert "cancelled: it holds its cell" in done.stdout and took < 8
        out, _ = waiter.communicate(timeout=30)
        assert waiter.returncode == 1 and "not reached (cancelled)" in out, out
    finally:
        if waiter.poll() is None:
            waiter.kill()
    assert not f.run.active[1] and f.events("cancelled")
    again = goal(ros_env, 1, "--cancel", "--timeout", "8")
    assert again.returncode == 1, again.stdout
    assert "robot 1: nothing to cancel: it has no goal (it is idle)" in again.stdout
    unknown = goal(ros_env, 9, "--cancel", "--timeout", "8")
    assert unknown.returncode == 2 and "unknown robot 9" in unknown.stdout


@pytest.mark.ros
def test_a_task_file_is_queued_whole_or_not_at_all(ros_env, fleet, tmp_path):
    f = fleet()
    path = tmp_path / "tasks.yaml"
    path.write_text("- goal: [2, 2]\n- goal: [4, 4]\n")  # the second is the obstacle
    done = goal(ros_env, "--tasks", path)
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"{path}:2: task 1 (submit_tasks-1): rejected: goal: cell (4, 4) is an obstacle" \
        in done.stderr and "nothing queued" in done.stderr
    time.sleep(0.3)
    assert not f.run.queue and not f.run.active.any()  # the good task does not run
    path.write_text("- goal: [2, 2]\n- goal: [3, 4]\n- xy: [4.5, 2.5]\n")  # metres too
    done = goal(ros_env, "--tasks", path)
    assert done.returncode == 0, done.stdout + done.stderr
    time.sleep(0.3)
    assert sorted(map(tuple, (e["cell"] for e in f.events("assigned")))) == [(2, 2), (2, 4),
                                                                             (3, 4)]
    path.write_text("- goal: [2, 2]\n- goal: [3, 4\n")
    done = goal(ros_env, "--tasks", path)
    assert done.returncode == 2 and f"{path}:3:" in done.stderr and "not valid YAML" in done.stderr


@pytest.mark.ros
def test_goal_any_during_an_instance_run_is_refused_at_once(ros_env, fleet):
    f = fleet("instance")
    done = goal(ros_env, "any", "--cell", "2", "2")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "instance source" in done.stdout + done.stderr
    assert not f.run.queue


@pytest.mark.ros
def test_the_time_estimate_follows_a_new_tick_period_at_once(ros_env, fleet):
    f = fleet()
    f.stop.set()  # this test ticks by hand
    f.ticker.join(5)
    for _ in range(30):
        f.goals.on_tick([], tick_seconds=0.5)
    for _ in range(2):  # `param set tick_period 0.1`
        f.goals.on_tick([], tick_seconds=0.1)
    assert f.goals._tick_seconds == pytest.approx(0.1, rel=0.1)
