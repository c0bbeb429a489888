"""`mapf-fleet record DIR`: record the fleet's topics into a rosbag2 (MCAP storage), like
`ros2 bag record -s mcap`, with the pure-Python `rosbags` library (no rosbag2 install needed).

What it records by default: /fleet/map, /fleet/state, /fleet/moves, /fleet/move_batches (the
policy processes' moves, one message per process and tick), /fleet/progress, /fleet/outcome
(subscribed at once, so nothing of a fleet started next to it is missed) and every
/robot_<i>/pose, /robot_<i>/goal and /robot_<i>/waypoint as they are discovered; with
`--namespace /fleet_a` the same topics of the fleet in /fleet_a (/fleet_a/fleet/state, ...).
`--topics T ...` records exactly those topics instead.

How it writes: subscriptions are raw (`raw=True`), so each message arrives as the CDR bytes that
rosbag2 itself stores, and is written as is with its receive time (system clock, ns). The
subscription QoS follows the publishers (`echo.choose_qos`): transient-local for the latched
map/outcome/goals/waypoints, so their last value is recorded even when published before the
recorder started; each topic's offered QoS profiles are stored in the bag, so `ros2 bag play`
republishes latched topics latched. The custom `mapf_fleet_interfaces` types are registered in
rosbags' ROS 2 Jazzy typestore from their .msg files, so the bag carries their definitions and
RIHS01 hashes. The bag is a rosbag2 of metadata version 9 (Jazzy), readable by `ros2 bag info`,
`ros2 bag play` and `rosbags.rosbag2.Reader`.

The bag survives a kill: rosbags' MCAP writer keeps its current chunk in memory until it holds
1 MiB (it has no chunk-size or flush option), so the recorder closes the chunk and flushes the
file after each fleet state (one per tick), after the outcome, and at least every
FLUSH_PERIOD_S: a killed recorder (even `kill -9`) loses at most the messages of the tick in
flight. Such a bag lacks its MCAP summary and metadata.yaml; `mapf-fleet render --run` reads
it anyway (`view.bag_salvage`) and says so.

Ready before tick 0 (`--expect TOPIC=COUNT ...`, as `up --bag` starts it): a message published
before the recorder's subscription is matched to its publisher is lost to the bag (the topics
are volatile but the latched ones), and `up`'s tick 0 waits only for the recorder's subscription
to the fleet state (the simulator's `state_recorder`). So with `--expect` the recorder subscribes
to the fleet state last: once each expected TOPIC has at least COUNT matched publishers (`up`:
every policy process's moves, one publisher per process on /fleet/move_batches, or /fleet/moves
with `per_robot_messages`; the simulator's progress) and every other volatile topic it records
has matched every publisher the graph shows (`BagRecorder.unmatched`), or after
`--expect-timeout` seconds (then it says which were missing). The readiness condition is stated
once, here; the simulator only checks that the recorder hears the state.

SIGINT or SIGTERM (or `--duration`) stops it: it closes the bag (metadata.yaml written) and
exits 0. The fleet launcher starts it as a child process with `recorder_command(bag_dir)` and
stops it with `stop_recorder(proc)`.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from mapf_fleet.ros import common

INTERFACES_PACKAGE = "mapf_fleet_interfaces"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
# The fleet's own topics and their types (docs/architecture.md, mapf_fleet.ros).
FLEET_TOPICS = {
    common.MAP_TOPIC: "nav_msgs/msg/OccupancyGrid",
    common.STATE_TOPIC: f"{INTERFACES_PACKAGE}/msg/FleetState",
    common.MOVES_TOPIC: f"{INTERFACES_PACKAGE}/msg/RobotMove",
    common.MOVE_BATCHES_TOPIC: f"{INTERFACES_PACKAGE}/msg/RobotMoves",
    common.PROGRESS_TOPIC: f"{INTERFACES_PACKAGE}/msg/FleetProgress",
    common.OUTCOME_TOPIC: f"{INTERFACES_PACKAGE}/msg/FleetOutcome",
    common.GOAL_EVENTS_TOPIC: f"{INTERFACES_PACKAGE}/msg/GoalEvent",  # every goal change
}


def default_topic_re(namespace: str = "") -> re.Pattern:
    """The topics recorded by default when discovered: the fleet's, in `namespace`."""
    prefix = re.escape("/" + namespace.strip("/")) if namespace.strip("/") else ""
    return re.compile(
        prefix + r"/(fleet/(map|state|moves|move_batches|progress|outcome|goal_events)"
        r"|robot_\d+/(pose|goal|goal_pose|waypoint))$")


DEFAULT_TOPIC_RE = default_topic_re()
READY_PREFIX = "mapf-fleet record: recording to"
# printed once, when the outcome and the run's final state (`done`) are both written: the
# outcome is published right after that state but on another topic, so it may arrive first
OUTCOME_PREFIX = "mapf-fleet record: outcome recorded"
RECORDER_NODE = "mapf_fleet_recorder"  # the simulator waits for its state subscription
DISCOVERY_PERIOD_S = 0.25
HOLD_CHECK_PERIOD_S = 0.05  # with `expect`: how often the matches are checked before tick 0
FLUSH_PERIOD_S = 1.0  # longest time a received message stays in memory only
OUTCOME_WAIT_S = 5.0  # `up` gone: how long the recorder waits for its stopped fleet's outcome


class RecordError(RuntimeError):
    """A bag cannot be written (its message names the directory or topic and the problem)."""


def interface_msg_dir() -> Path:
    """Where the .msg files of mapf_fleet_interfaces are: the installed share directory (the
    definitions the built message classes come from), else the source tree."""
    try:
        from ament_index_python.packages import get_package_share_directory

        installed = Path(get_package_share_directory(INTERFACES_PACKAGE)) / "msg"
        if any(installed.glob("*.msg")):
            return installed
    except (ImportError, LookupError, ValueError):
        pass
    from mapf_fleet.paths import SOURCE_ROOT

    source = SOURCE_ROOT / INTERFACES_PACKAGE / "msg"  # a checkout: the package beside mapf_fleet
    if any(source.glob("*.msg")):
        return source
    raise RecordError(f"no .msg files of {INTERFACES_PACKAGE} found (looked in the ament index "
                      f"and {source})")


def fleet_typestore(msg_dir: Path | None = None):
    """rosbags' ROS 2 Jazzy typestore with the mapf_fleet_interfaces messages registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    typestore = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for path in sorted((msg_dir or interface_msg_dir()).glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"{INTERFACES_PACKAGE}/msg/{path.stem}"))
    typestore.register(types)
    return typestore


def _duration(value):
    """(sec, nsec) of an rclpy Duration (rclpy reports "infinite" as the largest duration, which
    is also how rosbag2 writes it)."""
    from rosbags.interfaces import QosTime

    nanoseconds = int(getattr(value, "nanoseconds", 0))
    return QosTime(nanoseconds // 1_000_000_000, nanoseconds % 1_000_000_000)


def rosbags_qos(profile):
    """rosbags' Qos of an rclpy QoSProfile (the offered QoS stored for each topic)."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability)

    return Qos(history=QosHistory(int(profile.history)), depth=int(profile.depth),
               reliability=QosReliability(int(profile.reliability)),
               durability=QosDurability(int(profile.durability)),
               deadline=_duration(profile.deadline), lifespan=_duration(profile.lifespan),
               liveliness=QosLiveliness(int(profile.liveliness)),
               liveliness_lease_duration=_duration(profile.liveliness_lease_duration),
               avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions))


class BagRecorder:
    """Subscribes to topics on `node` and writes what arrives into a new rosbag2 (MCAP) at
    `bag_dir`. `topics` None: the fleet's topics in `namespace` (FLEET_TOPICS at once, the rest
    of `default_topic_re(namespace)` as discovered); else exactly those names. Call `discover()` periodically
    (the constructor arms a timer on the node for it) and `close()` once the node has stopped
    spinning. `expect` ({topic: publishers}): the fleet state is subscribed only once `ready`
    (see the module's doc), or after `expect_timeout` seconds."""

    def __init__(self, node, bag_dir, topics: list[str] | None = None, log=None,
                 namespace: str = "", expect: dict[str, int] | None = None,
                 expect_timeout: float = 120.0):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.rosbag2.errors import WriterError

        self.node = node
        self.announce = False  # `mapf-fleet record`: print OUTCOME_PREFIX on the outcome
        self.bag_dir = Path(bag_dir)
        self.log = log or (lambda text: print(text, file=sys.stderr, flush=True))
        self.topics = None if topics is None else list(dict.fromkeys(topics))
        self.pattern = default_topic_re(namespace)
        self.expect = dict(expect or {})  # checked before the bag's directory is made
        state = common.in_namespace(common.STATE_TOPIC, namespace)
        for topic, count in self.expect.items():
            if topic == state:
                raise RecordError(f"expected publishers of {topic}: the fleet state is what "
                                  "tick 0 waits for, subscribed last; expect other topics")
            if not self.wanted(topic) or int(count) < 1:
                raise RecordError(f"expected publishers {topic}={count}: not a topic this "
                                  "recorder records, or a count below 1")
        self.typestore = fleet_typestore()
        if self.bag_dir.exists():
            raise RecordError(f"{self.bag_dir} exists already: a rosbag2 is written into a new "
                              "directory")
        self.writer = Writer(self.bag_dir, version=9, storage_plugin=StoragePlugin.MCAP)
        try:
            self.writer.open()
        except (OSError, WriterError) as exc:
            raise RecordError(f"cannot create the bag {self.bag_dir}: {exc}") from None
        self._lock = threading.Lock()
        self._closed = False
        self._flushed = time.monotonic()
        self._flush_on = (common.in_namespace(common.STATE_TOPIC, namespace),
                          common.in_namespace(common.OUTCOME_TOPIC, namespace))
        self._subscriptions = {}  # topic -> (connection, subscription)
        self._skipped: set[str] = set()
        self.counts: dict[str, int] = {}
        self._state_topic = state
        self._last_state = None  # the CDR bytes of the last fleet state written
        self._outcome_written = False
        self.complete = False  # the outcome and the final state are written (`ended`)
        fleet = {common.in_namespace(name, namespace): type_name
                 for name, type_name in FLEET_TOPICS.items()}
        wanted = fleet if self.topics is None else {
            name: fleet[name] for name in self.topics if name in fleet}
        self._records_state = state in wanted
        # topic -> type, subscribed once every expected publisher is matched
        self._held = {state: wanted[state]} if self.expect and state in wanted else {}
        for name, type_name in wanted.items():
            if name not in self._held:
                self._subscribe(name, type_name, node.get_publishers_info_by_topic(name))
        self.discover()
        self._timer = node.create_timer(DISCOVERY_PERIOD_S, self._on_timer)
        self._hold_timer = None
        if self._held:
            self._hold_deadline = time.monotonic() + expect_timeout
            self._expect_timeout = expect_timeout
            self._hold_timer = node.create_timer(HOLD_CHECK_PERIOD_S, self._check_hold)

    @property
    def ready(self) -> bool:
        """Every topic is subscribed, the fleet state included (with `expect`: once matched)."""
        return not self._held

    def unmatched(self, expected_only: bool = False) -> list[str]:
        """What keeps the recorder from being ready, e.g. "/fleet/move_batches (1 of 2
        publishers matched)": each expected topic with fewer matched publishers than expected,
        each other volatile topic recorded with fewer than the graph shows (the latched ones
        keep their last message for a subscription matched late)."""
        from mapf_fleet.ros.echo import is_latched_topic

        missing = []
        for topic, count in self.expect.items():
            entry = self._subscriptions.get(topic)
            matched = entry[1].get_publisher_count() if entry else 0
            if matched < count:
                missing.append(f"{topic} ({matched} of {count} publishers matched)")
        if expected_only:
            return missing
        for topic, (_, subscription) in list(self._subscriptions.items()):
            if topic in self.expect or is_latched_topic(topic):
                continue
            known, matched = self.node.count_publishers(topic), subscription.get_publisher_count()
            if matched < known:
                missing.append(f"{topic} ({matched} of {known} publishers matched)")
        return missing

    def _check_hold(self):
        """With `expect`: subscribe the held fleet state once nothing is unmatched, or at the
        deadline (saying what was missing)."""
        if self._closed or not self._held:
            return
        timed_out = time.monotonic() >= self._hold_deadline
        # the graph's count of every robot's topics only once the policy processes are matched
        missing = self.unmatched(expected_only=not timed_out) or self.unmatched()
        if missing and not timed_out:
            return
        if missing:
            self.log(f"mapf-fleet record: subscribing to the fleet state after "
                     f"{self._expect_timeout:g} s without {', '.join(missing)}: the bag may "
                     "lack their first messages")
        held, self._held = self._held, {}
        for name, type_name in held.items():
            self._subscribe(name, type_name, self.node.get_publishers_info_by_topic(name))
        self._hold_timer.cancel()

    def _on_timer(self):
        self.discover()
        with self._lock:
            if not self._closed and time.monotonic() - self._flushed >= FLUSH_PERIOD_S:
                self._flush()

    def _flush(self):
        """Write the pending chunk to the file (the lock held): what a kill would lose."""
        storage = self.writer.storage
        chunk = getattr(storage, "chunk", None)
        if chunk is not None and chunk.bio.tell():
            storage.close_chunk()
        bio = getattr(storage, "bio", None)
        if bio is not None:
            bio.flush()
        self._flushed = time.monotonic()

    def wanted(self, topic: str) -> bool:
        return bool(self.pattern.fullmatch(topic)) if self.topics is None else topic in self.topics

    def discover(self):
        """Subscribe to every wanted topic of the graph not recorded yet."""
        if self._closed:
            return
        for name, types in self.node.get_topic_names_and_types():
            if name in self._subscriptions or name in self._skipped or name in self._held \
                    or not self.wanted(name):
                continue
            self._subscribe(name, types[0], self.node.get_publishers_info_by_topic(name))

    def _subscribe(self, topic: str, type_name: str, publishers):
        from mapf_fleet.ros.echo import choose_qos, import_message_type, is_latched_topic

        try:
            msg_class = import_message_type(type_name)
            self.typestore.get_msgdef(type_name)
        except (ValueError, KeyError) as exc:
            self._skipped.add(topic)
            self.log(f"mapf-fleet record: not recording {topic}: type {type_name} unknown ({exc})")
            return
        qos = choose_qos(topic, publishers, depth=1000)
        # the publishers' offered QoS; none discovered yet: what the fleet's publishers offer
        offered = [rosbags_qos(p.qos_profile) for p in publishers] or [
            rosbags_qos(choose_qos(topic, [], depth=1 if is_latched_topic(topic) else 10))]
        with self._lock:
            connection = self.writer.add_connection(topic, type_name, typestore=self.typestore,
                                                     offered_qos_profiles=offered)
            self.counts[topic] = 0
        if topic == self._state_topic:
            self._state_class = msg_class
        subscription = self.node.create_subscription(
            msg_class, topic, lambda data, c=connection: self._write(c, data), qos, raw=True)
        self._subscriptions[topic] = (connection, subscription)

    def _write(self, connection, data: bytes):
        stamp = time.time_ns()
        with self._lock:
            if self._closed:
                return
            self.writer.write(connection, stamp, data)
            self.counts[connection.topic] += 1
            if connection.topic == self._state_topic:
                self._last_state = data
            elif connection.topic.endswith(common.OUTCOME_TOPIC):
                self._outcome_written = True
            if connection.topic in self._flush_on \
                    or time.monotonic() - self._flushed >= FLUSH_PERIOD_S:
                self._flush()  # a tick's state ends the tick: its messages reach the file
            ended = not self.complete and self._ended()
            self.complete = self.complete or ended
        if ended and self.announce:
            _say(f"{OUTCOME_PREFIX} on {connection.topic}")

    def _ended(self) -> bool:
        """The outcome is written and so is the run's final state (`done`), unless the fleet
        state is not recorded at all (the lock held)."""
        if not self._outcome_written:
            return False
        if not self._records_state:
            return True
        if self._last_state is None:
            return False
        from rclpy.serialization import deserialize_message

        return bool(deserialize_message(self._last_state, self._state_class).done)

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def close(self):
        """Close the bag (writes metadata.yaml); later messages are dropped. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self.writer.close()


def _parent_dies(within: float = 1.0) -> bool:
    """Whether the `up` that started this recorder is gone, or goes within `within` s. Its death
    sends SIGTERM (PR_SET_PDEATHSIG) when the thread that started the recorder ends, which under
    `kill -9` comes a moment before the process is gone and this one re-parented."""
    from mapf_fleet.stop_signals import PARENT_PID_ENV, parent_gone

    if not os.environ.get(PARENT_PID_ENV):
        return False  # not started by `up`
    deadline = time.monotonic() + within
    while not parent_gone():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.05)
    return True


def _wait_for_outcome(recorder: BagRecorder, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not recorder.complete:
        time.sleep(0.1)


def recorder_command(bag_dir, topics: list[str] | None = None, namespace: str = "",
                     python: str | None = None, expect: dict[str, int] | None = None,
                     expect_timeout: float = 120.0) -> list[str]:
    """The command line that records the fleet's topics into the new rosbag2 `bag_dir`, for a
    launcher to start as a child process (with the fleet's environment: ROS_DOMAIN_ID,
    ROS_AUTOMATIC_DISCOVERY_RANGE). It prints a line starting with READY_PREFIX on stdout once
    its subscriptions exist (with `expect`, the fleet state's only once those publishers are
    matched, or after `expect_timeout` s: `BagRecorder`); stop it with `stop_recorder`."""
    command = [python or sys.executable, "-m", "mapf_fleet.cli", "record", str(bag_dir)]
    if namespace.strip("/"):
        command += ["--namespace", namespace]
    if topics:
        command += ["--topics", *topics]
    if expect:
        command += ["--expect", *(f"{topic}={count}" for topic, count in expect.items()),
                    "--expect-timeout", f"{expect_timeout:g}"]
    return command


def stop_recorder(proc: subprocess.Popen, grace: float = 0.5, timeout: float = 10.0) -> int:
    """End a recorder started from `recorder_command`: after `grace` seconds (messages still in
    flight when the fleet ended), SIGINT, then wait up to `timeout` s for it to close the bag
    (SIGKILL after that: the bag then lacks metadata.yaml). Returns its exit status."""
    if proc.poll() is None:
        time.sleep(grace)
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mapf-fleet record", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bag_dir", metavar="DIR", help="the rosbag2 directory to create")
    parser.add_argument("--topics", nargs="+", metavar="TOPIC",
                        help="record exactly these topics (default: the fleet's topics)")
    parser.add_argument("--namespace", default="",
                        help="the fleet's namespace (`up --namespace`): record /NS/fleet/... and "
                             "/NS/robot_<i>/...")
    parser.add_argument("--duration", type=float, default=0.0,
                        help="stop after this many seconds (default: until SIGINT/SIGTERM)")
    parser.add_argument("--expect", nargs="+", metavar="TOPIC=COUNT", default=[],
                        help="subscribe to the fleet state (what `up`'s tick 0 waits for) only "
                             "once each TOPIC has COUNT matched publishers and every other "
                             "volatile topic recorded all its publishers (`up --bag`: every "
                             "policy process's moves)")
    parser.add_argument("--expect-timeout", type=float, default=120.0, metavar="SECONDS",
                        help="with --expect: subscribe to the state anyway after this long "
                             "(default 120)")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    expect = {}
    for item in args.expect:
        topic, _, count = item.rpartition("=")
        if not topic.startswith("/") or not count.isdigit() or int(count) < 1:
            parser.error(f"--expect {item}: give TOPIC=COUNT, an absolute topic name and a "
                         "count >= 1")
        expect[topic] = int(count)
    if args.expect_timeout <= 0:
        parser.error(f"--expect-timeout must be > 0 (got {args.expect_timeout:g})")
    if args.topics:
        bad = [t for t in args.topics if not t.startswith("/")]
        if bad:
            parser.error(f"topic names must be absolute: {', '.join(bad)}")
    if args.duration < 0:
        parser.error("--duration must be >= 0")
    from mapf_fleet.ros.echo import ros_command

    with ros_command(RECORDER_NODE) as (node, stop):
        if stop.event.is_set():
            return 0
        try:
            recorder = BagRecorder(node, args.bag_dir, args.topics, namespace=args.namespace,
                                   expect=expect, expect_timeout=args.expect_timeout)
        except RecordError as exc:
            print(f"mapf-fleet record: {exc}", file=sys.stderr)
            return 2
        recorder.announce = True
        try:
            print(f"{READY_PREFIX} {args.bag_dir}", flush=True)
            deadline = time.monotonic() + args.duration if args.duration else None
            while not stop.wait(0.2):
                if deadline is not None and time.monotonic() >= deadline:
                    break
            if stop.signum == signal.SIGTERM and _parent_dies():  # `up` was killed: the
                _wait_for_outcome(recorder, OUTCOME_WAIT_S)  # simulator, stopped with it, still
                # says how the run ended; keep that
        finally:
            recorder.close()
    counts = {topic: n for topic, n in recorder.counts.items()}
    _say(f"mapf-fleet record: wrote {sum(counts.values())} messages on {len(counts)} topics to "
         f"{args.bag_dir}")
    return 0


def _say(line: str) -> None:
    """A line on stdout, which is `up`'s pipe when it started the recorder: gone with a killed
    `up`, and the bag must still be closed."""
    try:
        print(line, flush=True)
    except (BrokenPipeError, OSError):
        pass
