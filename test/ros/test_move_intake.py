"""The simulator's move intake in one process (rclpy, no other processes): the moves queued on
the subscription are all taken by the callback the executor runs for the first of them (the
executor takes one message per wait, rebuilding its wait set for each), and a tick's moves of
other ticks or episodes are still dropped."""

from __future__ import annotations

import time

import pytest


def _move(episode, tick, robot, action):
    from mapf_fleet_interfaces.msg import RobotMove

    ranking = [action] + [a for a in range(5) if a != action]
    return RobotMove(episode=episode, tick=tick, robot_id=robot, action=action,
                     preferences=ranking, requested=[(robot + 1) % 64], messages_received=1)


@pytest.mark.ros
def test_one_callback_takes_every_queued_move(rclpy_context):
    from mapf_fleet_interfaces.msg import RobotMove
    from rclpy.executors import SingleThreadedExecutor

    from mapf_fleet.fleet.lockstep import FleetTicker
    from mapf_fleet.ros import common, fleet_io

    n = 64
    node = rclpy_context.create_node("mapf_simulator")
    sender = rclpy_context.create_node("moves_sender")
    ticker = FleetTicker(n, episode=7)
    fleet_io.FleetChannels(node, ticker, common.MapGeometry(1.0))
    pub = sender.create_publisher(RobotMove, common.rel(common.MOVES_TOPIC),
                                  common.reliable_qos(1000))
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        deadline = time.monotonic() + 20
        while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        pub.publish(_move(7, 1, 0, 1))  # a later tick: dropped
        pub.publish(_move(8, 0, 1, 1))  # another run: dropped
        for i in range(n):
            pub.publish(_move(7, 0, i, i % 5))
        time.sleep(2.0)  # every message delivered to the subscription's queue
        executor.spin_once(timeout_sec=5.0)  # one wait, one callback
        decisions = ticker.collect(0.0)
        assert decisions.missing == []
        assert decisions.actions.tolist() == [i % 5 for i in range(n)]
        assert decisions.requested == [[(i + 1) % n] for i in range(n)]
    finally:
        executor.shutdown()
        sender.destroy_node()
        node.destroy_node()
