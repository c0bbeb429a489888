"""`mapf-fleet echo TOPIC` (messages as YAML, like `ros2 topic echo`) and `mapf-fleet topics`."""

from __future__ import annotations

import argparse
import importlib
import sys
import threading
import time

import yaml

from mapf_fleet.ros import common


def message_to_dict(msg):
    """Plain Python (dict/list/scalars) of a ROS message, field by field."""
    if hasattr(msg, "get_fields_and_field_types"):
        return {name: message_to_dict(getattr(msg, name))
                for name in msg.get_fields_and_field_types()}
    if isinstance(msg, (list, tuple)) or type(msg).__name__ == "ndarray":
        return [message_to_dict(v) for v in msg]
    if hasattr(msg, "tolist"):  # array.array and numpy scalars
        return msg.tolist()
    return msg


def import_message_type(type_name: str):
    """'pkg/msg/Name' -> the class (ValueError naming the type when there is none)."""
    parts = type_name.split("/")
    try:
        package, kind, name = parts
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ValueError, ImportError, AttributeError):
        raise ValueError(f"--type: no message type {type_name!r} (expected pkg/msg/Name, e.g. "
                         f"nav_msgs/msg/OccupancyGrid)") from None


def _start(node_name: str):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    common.prepare_environment()
    rclpy.init(args=[node_name])
    node = rclpy.create_node(node_name)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    return node, common.SpinThread(executor).start()


def _stop(node, spinner):
    import rclpy

    spinner.stop()
    node.destroy_node()
    rclpy.try_shutdown()


def topics_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mapf-fleet topics", description="list topics and types")
    parser.add_argument("--wait", type=float, default=2.0, help="seconds of discovery")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    node, spinner = _start("mapf_fleet_topics")
    try:
        time.sleep(args.wait)
        for name, types in sorted(node.get_topic_names_and_types()):
            print(f"{name} [{', '.join(types)}]")
    finally:
        _stop(node, spinner)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mapf-fleet echo", description=__doc__)
    parser.add_argument("topic")
    parser.add_argument("--type", help="message type pkg/msg/Name (default: discovered)")
    parser.add_argument("--once", action="store_true", help="print one message and exit")
    parser.add_argument("-n", type=int, default=0, help="exit after this many messages")
    parser.add_argument("--timeout", type=float, default=10.0,
                        help="seconds to wait for the topic to appear")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    limit = 1 if args.once else args.n
    node, spinner = _start("mapf_fleet_echo")
    try:
        type_name = args.type
        deadline = time.monotonic() + args.timeout
        while type_name is None and time.monotonic() < deadline:
            found = dict(node.get_topic_names_and_types()).get(args.topic)
            if found:
                type_name = found[0]
            else:
                time.sleep(0.1)
        if type_name is None:
            print(f"mapf-fleet echo: topic {args.topic} not found within {args.timeout} s",
                  file=sys.stderr)
            return 1
        msg_type = import_message_type(type_name)
        publishers = node.get_publishers_info_by_topic(args.topic)
        from rclpy.qos import DurabilityPolicy

        latched = publishers and all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                     for p in publishers)
        qos = common.latched_qos() if latched else common.reliable_qos(100)
        done = threading.Event()
        count = [0]
        lock = threading.Lock()

        def on_message(msg):
            with lock:
                if done.is_set():
                    return
                print(yaml.safe_dump(message_to_dict(msg), sort_keys=False).rstrip())
                print("---", flush=True)
                count[0] += 1
                if limit and count[0] >= limit:
                    done.set()

        node.create_subscription(msg_type, args.topic, on_message, qos)
        try:
            while not done.wait(0.2):
                pass
        except KeyboardInterrupt:
            pass
    finally:
        _stop(node, spinner)
    return 0
