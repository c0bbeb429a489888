"""`mapf-fleet goal` asks again when a reply is lost (a service reply sent before the server
matched the client's reply reader: seen while the machine was loaded), but never queues tasks
twice: once the fleet's goal events show the request arrived, it stops asking."""

from __future__ import annotations

from mapf_fleet.ros.goal_cli import _ask


class _Future:
    def __init__(self, answered: bool):
        self.answered = answered

    def done(self) -> bool:
        return self.answered


def test_a_lost_reply_is_asked_again_within_the_timeout():
    sent = []

    def send():
        sent.append(_Future(answered=len(sent) == 2))  # the first two replies are lost
        return sent[-1]

    future = _ask(send, timeout=6.0, signals=None, attempts=4)
    assert future is sent[2] and len(sent) == 3


def test_no_answer_gives_up_at_the_timeout_and_stop_ends_the_asking():
    sent = []

    def send():
        sent.append(_Future(answered=False))
        return sent[-1]

    assert _ask(send, timeout=2.0, signals=None, attempts=2) is None and len(sent) == 2
    sent.clear()
    assert _ask(send, timeout=4.0, signals=None, attempts=4, stop=lambda: True) is None
    assert len(sent) == 1  # the request arrived (goal events): not sent twice


def test_goal_for_a_robot_the_fleet_does_not_have_is_refused_at_once(ros_env):
    """The fleet state names 8 robots: `goal 42` says so in seconds (exit 2), instead of
    waiting out --timeout for an action server that will never come."""
    import os
    import subprocess
    import sys
    import threading
    import time

    import pytest

    rclpy = pytest.importorskip("rclpy")
    from mapf_fleet_interfaces.msg import FleetState

    # both ROS processes stay on loopback: this one's rclpy reads os.environ and the CLI gets
    # env=ros_env, each with the test's own domain (`ros_env`, test/conftest.py)
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert ros_env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("fake_fleet", context=context)
    pub = node.create_publisher(FleetState, "/fleet/state", 10)
    stop = threading.Event()

    def publish():
        while not stop.wait(0.2):
            pub.publish(FleetState(rows=list(range(8)), cols=list(range(8))))

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    try:
        started = time.monotonic()
        done = subprocess.run([sys.executable, "-m", "mapf_fleet.cli", "goal", "42", "--cell",
                               "1", "1", "--timeout", "60"], env=ros_env, capture_output=True,
                              text=True, timeout=120)
        assert done.returncode == 2, done.stderr
        assert "robot 42: the fleet has 8 robots (0..7)" in done.stderr
        assert time.monotonic() - started < 45
    finally:
        stop.set()
        thread.join(2)
        node.destroy_node()
        rclpy.try_shutdown(context=context)
