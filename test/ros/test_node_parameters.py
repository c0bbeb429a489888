"""ROS parameters of the fleet's nodes as ROS users handle them: every policy node keeps its
parameter services whatever the process layout (issue 17 item 16), and a parameter set at
runtime either takes effect or is refused with a reason (item 11)."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import pytest

RUN = [sys.executable, "-m", "mapf_fleet.ros.run"]


@pytest.fixture
def rclpy_node(ros_env):
    """An rclpy context and a spun client node in this process (the test's own domain)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from mapf_fleet.ros import common

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("parameter_test_client", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    spinner = common.SpinThread(executor).start()
    try:
        yield node, executor, context
    finally:
        spinner.stop()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def _wait(future, timeout=20.0):
    deadline = time.monotonic() + timeout
    while not future.done() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert future.done(), "no answer from the parameter service"
    return future.result()


@pytest.mark.ros
def test_every_robot_hosted_in_one_process_has_parameter_services(ros_env, checkpoints,
                                                                   rclpy_node):
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    node, _, _ = rclpy_node
    proc = subprocess.Popen(RUN + ["policy", "--robots", "0-3", "--ros-args", "-p",
                                   f"checkpoint:={checkpoints['dhc']}"],
                            env=ros_env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    try:
        for robot in range(4):
            client = AsyncParameterClient(node, f"mapf_policy_{robot}")
            assert client.wait_for_services(timeout_sec=60.0), \
                f"robot {robot}: no parameter services"
            values = _wait(client.get_parameters(["robot_id", "checkpoint"])).values
            assert values[0].integer_value == robot
            assert values[1].string_value == checkpoints["dhc"]
            # read once at start-up: a change is refused with the reason, not silently ignored
            result = _wait(client.set_parameters([Parameter("comm_timeout", value=9.0)]))
            assert not result.results[0].successful
            assert "read when the policy node starts" in result.results[0].reason
    finally:
        proc.terminate()
        proc.wait(20)
