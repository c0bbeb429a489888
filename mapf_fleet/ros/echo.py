"""`mapf-fleet echo TOPIC` (messages as YAML, like `ros2 topic echo`) and `mapf-fleet topics`
(like `ros2 topic list -t`).

Both commands behave as the ROS 2 CLI does on a busy graph:
- `echo` subscribes with the QoS of the topic's publishers (as `ros2 topic echo` does): it waits,
  bounded by `--timeout`, until a publisher is discovered, and takes its reliability and
  durability. A topic seen only through its subscribers at first (a fleet whose policy processes
  are discovered before the simulator) no longer gets a volatile subscription to a latched topic.
  With no publisher in time, the fleet's latched topics (map, outcome, goals, waypoints) are
  subscribed transient-local, every other topic reliable and volatile.
- `topics` waits until discovery settles (topics and nodes unchanged for `--settle` seconds, at
  most `--wait` seconds in all) instead of a fixed pause: Fast DDS discovers some participants
  only at their next announcement, seconds after the others.
- SIGINT and SIGTERM end either command cleanly (exit 0, no traceback).
"""

from __future__ import annotations

import argparse
import importlib
import os
import re
import sys
import threading
import time
from contextlib import contextmanager

import yaml

from mapf_fleet.ros import common
from mapf_fleet.stop_signals import StopSignals

# Topics the fleet publishes latched (reliable, transient local); relative to any namespace.
LATCHED_TOPIC_RE = re.compile(r"(^|/)(fleet/(map|outcome)|robot_\d+/(goal|waypoint))$")


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
    """'pkg/msg/Name' -> the class; ValueError naming the type when it cannot be imported."""
    parts = type_name.split("/")
    if len(parts) == 2:  # pkg/Name, as `ros2 topic echo` accepts
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"message type {type_name!r} is not of the form pkg/msg/Name")
    package, kind, name = parts
    try:
        module = importlib.import_module(f"{package}.{kind}")
    except ImportError:
        raise ValueError(f"message type {type_name!r}: no interface package {package!r} "
                         "installed") from None
    cls = getattr(module, name, None)
    if cls is None:
        raise ValueError(f"message type {type_name!r}: {package} has no {kind} {name!r}")
    if not hasattr(cls, "get_fields_and_field_types"):
        raise ValueError(f"{type_name!r} is not a message type")
    return cls


def is_latched_topic(topic: str) -> bool:
    """True for the topics the fleet publishes transient-local (map, outcome, goals, waypoints)."""
    return bool(LATCHED_TOPIC_RE.search(topic))


def choose_qos(topic: str, publishers, depth: int = 100):
    """The subscription QoS for `topic` given its discovered publishers' endpoint infos, as
    `ros2 topic echo` chooses it: reliable only when every publisher is reliable, transient-local
    only when every publisher is; with no publisher known, the fleet's own choice for the topic
    (transient-local for its latched topics, else reliable volatile)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    if not publishers:
        return common.latched_qos(depth) if is_latched_topic(topic) else common.reliable_qos(depth)
    profiles = [p.qos_profile for p in publishers]
    reliable = all(q.reliability == ReliabilityPolicy.RELIABLE for q in profiles)
    latched = all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in profiles)
    return QoSProfile(
        depth=depth, history=HistoryPolicy.KEEP_LAST,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def start_node(node_name: str):
    """rclpy (without its signal handlers: the caller owns SIGINT/SIGTERM), one node, spun in a
    thread. Returns (node, spinner)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    common.prepare_environment()
    rclpy.init(args=[node_name], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(node_name)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    return node, common.SpinThread(executor).start()


def stop_node(node, spinner):
    import rclpy

    spinner.stop()
    node.destroy_node()
    rclpy.try_shutdown()


@contextmanager
def ros_command(node_name: str):
    """(node, stop signals) for the duration of a command; shuts everything down on the way out,
    whether it ends normally or by a signal."""
    stop = StopSignals().install()
    node = spinner = None
    try:
        node, spinner = start_node(node_name)
        yield node, stop
    finally:
        if node is not None:
            stop_node(node, spinner)
        stop.restore()


def _graph(node):
    topics = sorted((name, list(types)) for name, types in node.get_topic_names_and_types())
    return topics, sorted(node.get_node_names_and_namespaces())


def _only_self(node, nodes) -> bool:
    """Whether the discovered (name, namespace) pairs `nodes` show no node but `node`."""
    own = (node.get_name(), node.get_namespace())
    return all(entry == own for entry in nodes)


def settled_topics(node, stop: StopSignals, settle: float, timeout: float,
                   poll: float = 0.1) -> tuple[list[tuple[str, list[str]]], bool]:
    """The graph's topics once discovery has settled: another node has been discovered and
    neither the topics (names and types) nor the nodes have changed for `settle` seconds since,
    or `timeout` seconds have passed. Returns (topics, settled). Fast DDS sometimes discovers a
    participant only at its next periodic announcement, about 2.5 s later than the others, so
    `settle` should stay above that. A graph showing only this node is not settled: on a loaded
    machine the first participant can take longer than `settle` to show up (an empty list was
    printed under CI load), and a graph with no other node is never what the user asked about."""
    start = time.monotonic()
    last = _graph(node)
    changed = start
    while True:
        now = time.monotonic()
        if not _only_self(node, last[1]) and now - changed >= settle:
            return last[0], True
        if now - start >= timeout or stop.wait(poll):
            return last[0], False
        current = _graph(node)
        if current != last:
            last, changed = current, time.monotonic()


def topics_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="mapf-fleet topics", description="list the graph's topics and their types, once "
        "discovery has settled (like `ros2 topic list -t`)")
    parser.add_argument("--wait", type=float, default=10.0,
                        help="at most this many seconds of discovery (default 10)")
    parser.add_argument("--settle", type=float, default=3.0,
                        help="discovery has settled when the topics and nodes have not changed "
                             "for this many seconds (default 3)")
    parser.add_argument("--namespace", default="",
                        help="list only the topics of the fleet in this namespace (/fleet_a)")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if not args.wait > 0 or not args.settle > 0:
        parser.error("--wait and --settle must be > 0")
    with ros_command("mapf_fleet_topics") as (node, stop):
        topics, settled = settled_topics(node, stop, args.settle, args.wait)
        if stop.requested:
            return 0
        prefix = "/" + args.namespace.strip("/") + "/" if args.namespace.strip("/") else "/"
        for name, types in topics:
            if not name.startswith(prefix):
                continue
            print(f"{name} [{', '.join(types)}]")
        if not settled:
            why = ("no other node discovered"
                   if _only_self(node, node.get_node_names_and_namespaces())
                   else "discovery still changing")
            print(f"mapf-fleet topics: {why} after {args.wait:g} s; the list may be incomplete "
                  "(raise --wait; is the fleet on this ROS_DOMAIN_ID?)", file=sys.stderr)
    return 0


def _discover(node, stop: StopSignals, topic: str, type_name: str | None, deadline: float):
    """(type name or None, publishers): waits until the topic's type is known and one of its
    publishers is discovered, or the deadline passes, or a stop signal comes."""
    publishers = []
    while True:
        if type_name is None:
            found = dict(node.get_topic_names_and_types()).get(topic)
            if found:
                type_name = found[0]
        publishers = node.get_publishers_info_by_topic(topic)
        if type_name is not None and publishers:
            return type_name, publishers
        if time.monotonic() >= deadline or stop.wait(0.05):
            return type_name, publishers


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mapf-fleet echo", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("topic")
    parser.add_argument("--type", help="message type pkg/msg/Name (default: discovered)")
    parser.add_argument("--once", action="store_true", help="print one message and exit")
    parser.add_argument("-n", type=int, default=0, help="exit after this many messages")
    parser.add_argument("--timeout", type=float, default=10.0,
                        help="seconds to wait for the topic and a publisher to appear, and with "
                             "--once / -n for the messages (default 10)")
    parser.add_argument("--namespace", default="",
                        help="the fleet's namespace: TOPIC /fleet/map means /NS/fleet/map")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    args.topic = common.in_namespace(args.topic, args.namespace)
    limit = 1 if args.once else args.n
    msg_type = None
    if args.type is not None:
        try:
            msg_type = import_message_type(args.type)
        except ValueError as exc:
            print(f"mapf-fleet echo: {exc}", file=sys.stderr)
            return 2
    with ros_command("mapf_fleet_echo") as (node, stop):
        deadline = time.monotonic() + args.timeout
        type_name, publishers = _discover(node, stop, args.topic, args.type, deadline)
        if stop.requested:
            return 0
        if type_name is None:
            print(f"mapf-fleet echo: topic {args.topic} not found within {args.timeout:g} s",
                  file=sys.stderr)
            return 1
        if not publishers:  # what --timeout waits for: nothing would ever arrive
            print(f"mapf-fleet echo: no publisher of {args.topic} found within "
                  f"{args.timeout:g} s", file=sys.stderr)
            return 1
        offered = sorted({p.topic_type for p in publishers})
        if args.type is not None and args.type not in offered:
            print(f"mapf-fleet echo: topic {args.topic} has type {', '.join(offered)}, not "
                  f"--type {args.type}", file=sys.stderr)
            return 2
        if msg_type is None:
            try:
                msg_type = import_message_type(type_name)
            except ValueError as exc:
                print(f"mapf-fleet echo: topic {args.topic}: {exc}", file=sys.stderr)
                return 2
        qos = choose_qos(args.topic, publishers)
        done = threading.Event()
        count = [0]
        lock = threading.Lock()

        def on_message(msg):
            with lock:
                if done.is_set():
                    return
                try:
                    print(yaml.safe_dump(message_to_dict(msg), sort_keys=False).rstrip())
                    print("---", flush=True)
                except BrokenPipeError:  # `mapf-fleet echo T | head`: the reader has gone
                    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
                    done.set()
                    return
                count[0] += 1
                if limit and count[0] >= limit:
                    done.set()

        node.create_subscription(msg_type, args.topic, on_message, qos)
        # --once / -n: the messages are waited for --timeout s too (a publisher may be silent)
        deadline = time.monotonic() + args.timeout if limit else float("inf")
        while not done.is_set() and not stop.wait(0.1):
            if time.monotonic() > deadline:
                with lock:
                    done.set()
                    got = count[0]
                print(f"mapf-fleet echo: {got} of {limit} message{'s' if limit != 1 else ''} "
                      f"on {args.topic} within {args.timeout:g} s", file=sys.stderr)
                return 1
    return 0
