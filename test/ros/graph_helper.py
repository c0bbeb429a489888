"""Stand-in ROS processes for the echo/topics/record tests, run as
`python test/ros/graph_helper.py ROLE [options]` with the test's `ros_env`.

Roles (each prints "ready" once its entities exist, then spins until SIGINT/SIGTERM):
- latched TOPIC: publishes one OccupancyGrid (3x3 identity map, resolution 0.5) transient-local.
- subscriber TOPIC: a transient-local OccupancyGrid subscription only (as the fleet's policy
  hubs subscribe to /fleet/map before the simulator exists).
- best-effort TOPIC: publishes std_msgs/String "tick k" best-effort at 10 Hz.
- trickle N PERIOD: creates publishers on /trickle/t_00 ... one every PERIOD s (a fleet whose
  processes are discovered over several seconds); prints "ready" after the first, "done" after
  the last.
"""

from __future__ import annotations

import signal
import sys
import threading
import time


def main(argv: list[str]) -> int:
    import numpy as np
    import rclpy
    from nav_msgs.msg import OccupancyGrid
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    from mapf_fleet.ros import common

    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    common.prepare_environment()
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    role = argv[0]
    node = rclpy.create_node(f"graph_helper_{role.replace('-', '_')}")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = common.SpinThread(executor).start()
    grid = common.grid_to_occupancy(np.eye(3, dtype=np.uint8), common.MapGeometry(0.5))
    keep = []
    try:
        if role == "latched":
            keep.append(node.create_publisher(OccupancyGrid, argv[1], common.latched_qos()))
            keep[-1].publish(grid)
            print("ready", flush=True)
        elif role == "subscriber":
            keep.append(node.create_subscription(OccupancyGrid, argv[1], lambda _: None,
                                                 common.latched_qos()))
            print("ready", flush=True)
        elif role == "best-effort":
            pub = node.create_publisher(String, argv[1],
                                        QoSProfile(depth=10,
                                                   reliability=ReliabilityPolicy.BEST_EFFORT))
            print("ready", flush=True)
            tick = 0
            while not stop.wait(0.1):
                pub.publish(String(data=f"tick {tick}"))
                tick += 1
        elif role == "trickle":
            count, period = int(argv[1]), float(argv[2])
            for k in range(count):
                keep.append(node.create_publisher(String, f"/trickle/t_{k:02d}", 10))
                if k == 0:
                    print("ready", flush=True)
                if stop.wait(period):
                    break
            print("done", flush=True)
        else:
            print(f"graph_helper: unknown role {role!r}", file=sys.stderr)
            return 2
        stop.wait()
    finally:
        spinner.stop()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
