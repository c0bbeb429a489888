"""ROS parameters of the fleet's nodes as ROS users handle them: every policy node keeps its
parameter services whatever the process layout (`ros2 param` reaches each robot), and a
parameter set at runtime either takes effect or is refused with a reason."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import pytest

RUN = [sys.executable, "-m", "mapf_fleet.ros.run"]


@pytest.fixture
def rclpy_node(ros_env):
    """An rclpy context and a spun client node in this process (the test's own domain; ros_env
    (test/conftest.py) puts ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST in os.environ and the env
    of the subprocesses)."""
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert ros_env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
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


@pytest.mark.ros
def test_simulator_applies_runtime_parameters_and_refuses_the_rest(ros_env):
    """`ros2 param set /mapf_simulator tick_period 1.0` slows the ticks down from the next tick;
    a parameter read at start-up (max_steps) or a bad value is refused with the reason."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    from mapf_fleet.ros import common
    from mapf_fleet.ros.simulator_node import SimulatorNode

    rclpy.init(args=["test"])
    try:
        # no policy nodes: every tick waits decision_timeout (0.2 s) for the missing robots
        simulator = SimulatorNode(parameter_overrides=[
            Parameter("num_robots", value=2), Parameter("size", value=8),
            Parameter("startup_timeout", value=0.3), Parameter("decision_timeout", value=0.2),
            Parameter("max_steps", value=25), Parameter("progress_every", value=100)])
        client_node = rclpy.create_node("parameter_test_client")
        executor = SingleThreadedExecutor()
        executor.add_node(simulator)
        executor.add_node(client_node)
        spinner = common.SpinThread(executor).start()
        simulator.start()
        try:
            client = AsyncParameterClient(client_node, "mapf_simulator")
            assert client.wait_for_services(timeout_sec=20.0)
            deadline = time.monotonic() + 20
            while simulator.tick < 2 and time.monotonic() < deadline:
                time.sleep(0.05)
            result = _wait(client.set_parameters([Parameter("tick_period", value=1.0)]))
            assert result.results[0].successful, result.results[0].reason
            values = _wait(client.get_parameters(["tick_period"])).values
            assert values[0].double_value == 1.0
            # the tick running when it was set ends (its period was read at its start), then
            # the next one, the first of period 1.0, plays: from here on the ticks are slow
            set_at, deadline = simulator.tick, time.monotonic() + 30
            while simulator.tick < set_at + 2 and time.monotonic() < deadline:
                time.sleep(0.01)
            first, started = simulator.tick, time.monotonic()
            time.sleep(3.0)
            rate = (simulator.tick - first) / (time.monotonic() - started)
            assert rate < 1.5, f"{rate:.1f} ticks/s with tick_period 1.0 (0.2 s before)"
            for name, value, reason in [("max_steps", 1000, "read at start-up"),
                                        ("num_robots", 5, "read at start-up"),
                                        ("decision_timeout", -1.0, "must be > 0"),
                                        ("tick_period", -0.5, "must be >= 0")]:
                result = _wait(client.set_parameters([Parameter(name, value=value)]))
                assert not result.results[0].successful, name
                assert reason in result.results[0].reason, result.results[0].reason
            assert simulator.params["max_steps"] == 25
            _wait(client.set_parameters([Parameter("tick_period", value=0.0)]))
            assert simulator.finished.wait(30.0)
            assert simulator.run.steps == 25
        finally:
            spinner.stop()
            simulator.destroy_node()
            client_node.destroy_node()
    finally:
        rclpy.try_shutdown()
