"""The tick loop's ROS outlet logs at every level from one run: rclpy refuses a call site
(file and line) that logs at a severity other than its first ("Logger severity cannot be changed
between calls."), and one call site for all levels made the simulator's tick thread die at the
first warning after an info line (the first tick with a missed decision ended a 1,024-robot run
at tick 5: issue 40, Scale)."""

from __future__ import annotations

import pytest


@pytest.mark.ros
def test_the_outlet_logs_info_then_warning_then_error(rclpy_context):
    from mapf_fleet.ros.fleet_io import RosOutlet

    node = rclpy_context.create_node("outlet_logs")
    try:
        outlet = RosOutlet(node, channels=None, publish_state=None)
        for level in ("info", "warning", "error", "info", "warning"):
            outlet.log(level, f"a {level} line")  # raised ValueError at the first warning
        with pytest.raises(ValueError, match="level"):
            outlet.log("debug", "no such level here")
    finally:
        node.destroy_node()
