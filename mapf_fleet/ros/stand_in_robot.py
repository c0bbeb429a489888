"""Stand-in robots for real-robot mode (tests, demos): each publishes its pose on
`/robot_<i>/pose` and, when a waypoint arrives on `/robot_<i>/waypoint` (commanded by the
aggregator, the tick's arbiter), jumps there after a random delay (uniform in [0, max-delay]; a
delay beyond the aggregator's `arrival_timeout` leaves the robot in transit at the next tick). `--off-grid ID` makes robot ID report a pose outside the map from its first move
on (to exercise the aggregator's rejection).

    python -m mapf_fleet.ros.stand_in_robot --instance config/fleet/instance_small.yaml \\
        --max-delay 0.3 [--off-grid 2] [--resolution 1.0] [--origin X Y] [--robots 0-3]
    python -m mapf_fleet.ros.stand_in_robot --map building.yaml --cell-size 0.5 \\
        --num-robots 4 --seed 3      # the starts the aggregator draws for the same options

`--robots IDS` stands in for those robots only (the others are real ones).
"""

from __future__ import annotations

import argparse
import math
import random
import sys
import threading
import time

from mapf_fleet.entry import one_line_errors
from mapf_fleet.ros import common


@one_line_errors("stand_in_robot")
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="stand_in_robot", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--instance", help="instance YAML: robots start there")
    where.add_argument("--map", help="a MovingAI .map (with --scen) or a Nav2 map YAML: the "
                                     "starts the aggregator takes for the same options")
    parser.add_argument("--scen", default="", help="MovingAI .scen (with --map)")
    parser.add_argument("--num-robots", type=int, default=8,
                        help="robots drawn on --map without --scen (default 8)")
    parser.add_argument("--cell-size", type=float, default=0.0,
                        help="Nav2 --map: metres per cell (default: one pixel)")
    parser.add_argument("--origin", type=float, nargs=2, default=(0.0, 0.0), metavar=("X", "Y"),
                        help="the map's corner in metres, as the aggregator's origin_x/origin_y "
                             "(default 0 0; a Nav2 map has its own)")
    parser.add_argument("--robots", default="", metavar="IDS",
                        help="stand in for these robots only, e.g. 0-3,7 (default: all)")
    parser.add_argument("--max-delay", type=float, default=0.3, help="seconds, uniform delay")
    parser.add_argument("--off-grid", type=int, default=-1, help="robot reporting off the map")
    parser.add_argument("--resolution", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--namespace", default="", help="the fleet's ROS namespace "
                        "(up --namespace): topics /NAMESPACE/robot_<i>/...")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.max_delay < 0:
        parser.error(f"--max-delay must be >= 0, got {args.max_delay}")
    if not all(math.isfinite(v) for v in args.origin):
        parser.error(f"--origin must be finite numbers, got {args.origin}")
    common.prepare_environment()
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor

    from mapf_fleet.fleet.instances import InstanceSource
    from mapf_fleet.ros.run import parse_robot_ids

    source = InstanceSource(args.instance or "", args.map or "", args.scen, args.num_robots,
                            seed=args.seed, cell_size=args.cell_size)
    instance = source.load()
    geometry = common.MapGeometry(*(source.geometry() or (args.resolution, *args.origin)))
    ids = parse_robot_ids(args.robots) if args.robots else list(range(instance.num_agents))
    if ids and max(ids) >= instance.num_agents:
        raise ValueError(f"--robots {args.robots}: the instance has robots "
                         f"0..{instance.num_agents - 1}")
    rng = random.Random(args.seed)
    lock = threading.Lock()
    namespace = args.namespace.strip("/")
    from rclpy.signals import SignalHandlerOptions

    from mapf_fleet.ros.processes import stop_signals

    signals = stop_signals()  # SIGINT / SIGTERM: stop, exit 130 / 143
    closed = threading.Event()  # set (under `lock`) before the node is destroyed
    rclpy.init(args=["stand_in_robot"]
               + (["--ros-args", "-r", f"__ns:=/{namespace}"] if namespace else []),
               signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("mapf_stand_in_robots")
    poses = {i: common.cell_pose(int(r), int(c), geometry)
             for i, (r, c) in enumerate(instance.starts) if i in set(ids)}
    pubs = {i: node.create_publisher(PoseStamped, common.rel(common.pose_topic(i)),
                                     common.reliable_qos(10))
            for i in poses}
    moved = set()
    # like a real robot, each follows its latest waypoint only: a new waypoint replaces the one
    # it was driving to (that arrival never happens), the same waypoint again changes nothing
    heading: dict[int, tuple] = {}  # robot -> (target x, y, version)
    versions = {i: 0 for i in poses}

    def arrive(i, msg, version):
        with lock:
            if versions[i] != version:
                return  # superseded by a newer waypoint
            heading.pop(i, None)
            pose = PoseStamped()
            pose.header.frame_id = common.FRAME_ID
            pose.pose = msg.pose
            if i == args.off_grid:
                pose.pose.position.x = -5.0 * geometry.resolution  # left of the map
            poses[i] = pose
            moved.add(i)
        publish(i)

    def on_waypoint(i, msg):
        target = (msg.pose.position.x, msg.pose.position.y)
        with lock:
            if i in heading and heading[i][:2] == target:
                return  # already driving there
            versions[i] += 1
            heading[i] = (*target, versions[i])
            delay = rng.uniform(0.0, args.max_delay)
            version = versions[i]
        timer = threading.Timer(delay, arrive, (i, msg, version))
        timer.daemon = True
        timer.start()

    def publish(i):
        with lock:
            if closed.is_set():
                return  # a delayed arrival after the stop
            pose = poses[i]
            pose.header.stamp = node.get_clock().now().to_msg()
            pubs[i].publish(pose)

    for i in poses:
        node.create_subscription(PoseStamped, common.rel(common.waypoint_topic(i)),
                                 lambda msg, i=i: on_waypoint(i, msg), common.latched_qos(1))
    # a pose feed publishes continuously, like a localisation stack
    node.create_timer(0.2, lambda: [publish(i) for i in poses])
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    # a failed callback is logged with its traceback and ends the process with code 1
    spinner = common.SpinThread(executor).start()
    try:
        while not signals.requested and spinner.error is None:
            time.sleep(0.1)
    finally:
        spinner.stop()
        with lock:
            closed.set()
            node.destroy_node()
        rclpy.try_shutdown()
        signals.restore()
    return signals.exit_code or (1 if spinner.error is not None else 0)


if __name__ == "__main__":
    sys.exit(main())
