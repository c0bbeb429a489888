"""Bad pose feeds in one process (rclpy, no other processes): a NaN / infinite pose and a
two-cell jump reach the aggregator's pose callback and are rejected with one log line naming the
robot, the field and the value, the robot holds its cell, and the callback does not raise (it
used to, and the spin thread then stopped the executor without a word). A callback that does
raise is logged with its cause by `SpinThread`, which reports it to the process, and a
`SpinThread` stopped right after it started does stop."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
INSTANCE = REPO / "config" / "fleet" / "instance_small.yaml"


def _pose(x, y):
    from geometry_msgs.msg import PoseStamped

    msg = PoseStamped()
    msg.pose.position.x, msg.pose.position.y = float(x), float(y)
    return msg


@pytest.mark.ros
def test_aggregator_rejects_nan_inf_and_jumping_poses_with_one_line_each(rclpy_context, capfd):
    from rclpy.parameter import Parameter

    from mapf_fleet.ros.aggregator_node import FleetStateAggregator

    node = FleetStateAggregator(parameter_overrides=[
        Parameter("instance_file", value=str(INSTANCE))])
    try:
        cell = node.geometry.cell_to_xy
        node._on_pose(0, _pose(*cell(0, 0)))                 # robot 0 starts at (0, 0)
        node._on_pose(1, _pose(*cell(7, 7)))
        capfd.readouterr()
        for _ in range(3):  # a feed repeats its bad pose, between good ones: no flood
            node._on_pose(1, _pose(*cell(7, 7)))
            node._on_pose(1, _pose(float("nan"), 7.5))       # used to raise ValueError
            node._on_pose(0, _pose(float("inf"), 0.5))       # used to raise OverflowError
        node._on_pose(0, _pose(*cell(2, 0)))                 # (0, 0) -> (2, 0): a jump
        time.sleep(0.2)
        err = capfd.readouterr().err
        lines = [line for line in err.splitlines() if "pose rejected" in line]
        assert len(lines) == 3, err                          # one line per robot and reason
        nan_line = next(line for line in lines if "robot 1:" in line)
        assert "pose.position.x is nan" in nan_line and "holds its last valid cell (7, 7)" in nan_line
        inf_line = next(line for line in lines if "robot 0:" in line and "inf" in line)
        assert "pose.position.x is inf" in inf_line
        jump_line = next(line for line in lines if "jump" in line)
        assert "robot 0:" in jump_line and "jump of 2 cells from cell 0,0 to 2,0" in jump_line
        # the robots hold their last valid cells; the jump's cell still counts as occupied
        assert node.positions[0].tolist() == [0, 0] and node.positions[1].tolist() == [7, 7]
        assert sorted(node._rejected_reason) == [0, 1]
        assert node._reported[0] == (2, 0)
        node._on_pose(0, _pose(*cell(1, 0)))                 # back to one move away: accepted
        assert 0 not in node._rejected_reason and node._reported[0] == (1, 0)
    finally:
        node.destroy_node()


@pytest.mark.ros
def test_spin_thread_logs_a_failing_callback_and_reports_it(rclpy_context, capfd):
    from rclpy.executors import SingleThreadedExecutor

    from mapf_fleet.ros.common import SpinThread

    node = rclpy_context.create_node("failing_callback")
    calls = []

    def callback():
        calls.append(1)
        raise ValueError("cannot convert float NaN to integer")

    node.create_timer(0.05, callback)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    failed = threading.Event()
    spinner = SpinThread(executor, on_error=lambda exc: failed.set()).start()
    try:
        assert failed.wait(10.0), "the failure was not reported"
        assert isinstance(spinner.error, ValueError)
        time.sleep(0.2)
        err = capfd.readouterr().err
        assert "a callback failed: ValueError('cannot convert float NaN to integer')" in err
        assert "Traceback" in err and "in callback" in err
    finally:
        spinner.stop()
        node.destroy_node()
    assert len(calls) == 1  # it stopped spinning: the process ends non-zero (spin loops)


@pytest.mark.ros
def test_spin_thread_stopped_at_once_ends_its_thread(rclpy_context):
    """`stop()` right after `start()`, many times, with the GIL switching between threads as
    often as it can and a busy thread competing for it: the spin thread has ended when `stop()`
    returns. With rclpy's own `Executor.shutdown()` racing the spinning thread (what SpinThread
    did until stop 27), a few in a hundred were left waiting forever without the executor's
    guard condition, and destroying the node then blocked (an `echo` hung on SIGINT in CI)."""
    from rclpy.executors import SingleThreadedExecutor

    from mapf_fleet.ros.common import SpinThread

    node = rclpy_context.create_node("spin_stop_race")
    busy_until = time.monotonic() + 120.0
    done = threading.Event()

    def busy():
        while not done.is_set() and time.monotonic() < busy_until:
            pass

    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    threading.Thread(target=busy, daemon=True).start()
    stuck = 0
    try:
        for _ in range(150):
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            spinner = SpinThread(executor).start()
            spinner.stop(timeout=2.0)
            stuck += spinner.running
    finally:
        done.set()
        sys.setswitchinterval(interval)
        node.destroy_node()
    assert stuck == 0, f"{stuck} of 150 spin threads still running after stop()"
