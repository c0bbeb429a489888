"""The simulator commands only the robots whose waypoint changed (issue 40, Scale: every robot's
waypoint every tick was a large share of a 1,024-robot tick): the topic is latched, so a robot
that stays still holds its current waypoint, and a subscriber that comes late gets every
robot's current one."""

from __future__ import annotations

import time

import pytest


@pytest.mark.ros
def test_only_changed_waypoints_are_sent_and_late_subscribers_get_all(rclpy_context):
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor

    from mapf_fleet.fleet.lockstep import FleetTicker
    from mapf_fleet.ros import common, fleet_io

    geometry = common.MapGeometry(1.0)
    node = rclpy_context.create_node("mapf_simulator")
    listener = rclpy_context.create_node("waypoint_listener")
    channels = fleet_io.FleetChannels(node, FleetTicker(3, episode=1), geometry)
    got = {i: [] for i in range(3)}

    def listen(on, into):
        for i in range(3):
            on.create_subscription(PoseStamped, common.rel(common.waypoint_topic(i)),
                                   lambda msg, i=i: into[i].append(
                                       geometry.xy_to_cell(msg.pose.position.x,
                                                           msg.pose.position.y)),
                                   common.latched_qos(1))

    listen(listener, got)
    executor = SingleThreadedExecutor()
    executor.add_node(listener)

    def spin(seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)

    try:
        deadline = time.monotonic() + 20
        while any(p.get_subscription_count() < 1 for p in channels.waypoint_pubs) and \
                time.monotonic() < deadline:
            time.sleep(0.05)
        channels.publish_waypoints([[1, 1], [2, 2], [3, 3]], changed_only=True)  # first: all
        spin(1.0)
        channels.publish_waypoints([[1, 2], [2, 2], [3, 3]], changed_only=True)  # robot 0 moves
        spin(1.0)
        assert got == {0: [(1, 1), (1, 2)], 1: [(2, 2)], 2: [(3, 3)]}
        late, later = rclpy_context.create_node("late_listener"), {i: [] for i in range(3)}
        listen(late, later)
        executor.add_node(late)
        spin(3.0)
        assert later == {0: [(1, 2)], 1: [(2, 2)], 2: [(3, 3)]}   # each robot's current one
    finally:
        executor.shutdown()
        for n in (listener, node):
            n.destroy_node()
