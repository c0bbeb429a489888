"""`mapf-fleet record` (mapf_fleet/ros/bag.py): a rosbag2 with MCAP storage of
the fleet's topics, written with `rosbags`, read back with `rosbags` and compared with the JSON
record of the same run."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mapf_fleet.ros.bag import READY_PREFIX, fleet_typestore, recorder_command, stop_recorder

CLI = [sys.executable, "-m", "mapf_fleet.cli"]
MCAP_MAGIC = b"\x89MCAP0\r\n"


def start_recorder(bag_dir, env, topics=None) -> subprocess.Popen:
    # env is ros_env (test/conftest.py): ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, own domain
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    proc = subprocess.Popen(recorder_command(bag_dir, topics), env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    line = proc.stdout.readline()
    if not line.startswith(READY_PREFIX):
        proc.kill()
        pytest.fail(f"recorder not ready: {line!r} {proc.stderr.read()}")
    return proc


def read_bag(bag_dir):
    """{topic: [(timestamp, message)]} and the bag's metadata, read with rosbags."""
    from rosbags.rosbag2 import Reader

    typestore = fleet_typestore()
    messages = {}
    with Reader(bag_dir) as reader:
        for connection in reader.connections:
            messages.setdefault(connection.topic, [])
        for connection, stamp, raw in reader.messages():
            messages[connection.topic].append(
                (stamp, typestore.deserialize_cdr(raw, connection.msgtype)))
        types = {c.topic: c.msgtype for c in reader.connections}
    return messages, types


def test_bag_type_hashes_equal_rosidl_hashes():
    """The typestore built from the .msg files gives the RIHS01 hashes rosidl generated for the
    built interfaces (what `ros2 bag play` and the live publishers use)."""
    from mapf_fleet.ros.bag import interface_msg_dir

    typestore = fleet_typestore()
    checked = 0
    for path in interface_msg_dir().glob("*.json"):
        name = f"mapf_fleet_interfaces/msg/{path.stem}"
        hashes = {h["type_name"]: h["hash_string"] for h in json.loads(path.read_text())["type_hashes"]}
        assert typestore.hash_rihs01(name) == hashes[name], name
        checked += 1
    if checked == 0:
        pytest.skip("no rosidl type-description JSON next to the .msg files (source tree)")


def test_recorder_command_runs_the_record_subcommand(tmp_path):
    command = recorder_command(tmp_path / "bag", topics=["/fleet/state"])
    assert command[1:] == ["-m", "mapf_fleet.cli", "record", str(tmp_path / "bag"),
                           "--topics", "/fleet/state"]


@pytest.mark.ros
def test_record_refuses_an_existing_directory(tmp_path, ros_env):
    assert ros_env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"  # test/conftest.py
    done = subprocess.run([*CLI, "record", str(tmp_path)], env=ros_env, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"mapf-fleet record: {tmp_path} exists already: a rosbag2 is written into a new directory"]


@pytest.mark.ros
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_record_closes_the_bag_on_signal(tmp_path, ros_env, signum):
    bag = tmp_path / "bag"
    proc = start_recorder(bag, ros_env, topics=["/fleet/state", "/test/other"])
    proc.send_signal(signum)
    out, err = proc.communicate(timeout=15)
    assert proc.returncode == 0, err
    assert "Traceback" not in err, err
    assert "wrote 0 messages on 1 topics" in out, out
    assert (bag / "metadata.yaml").exists()
    messages, types = read_bag(bag)
    assert types == {"/fleet/state": "mapf_fleet_interfaces/msg/FleetState"}


@pytest.mark.ros
@pytest.mark.slow
def test_recorded_fleet_matches_json_record(tmp_path, ros_env, checkpoints):
    """A short simulated fleet with `mapf-fleet record` beside it: the bag's /fleet/state holds
    every tick of the run with the positions of the JSON record."""
    bag, record = tmp_path / "fleet_bag", tmp_path / "rec.json"
    recorder = start_recorder(bag, ros_env)
    try:
        up = subprocess.run([*CLI, "up", "--checkpoint", checkpoints["dhc"], "--num-robots", "4",
                             "--size", "8", "--seed", "5", "--max-steps", "24", "--record",
                             str(record), "--quiet"], env=ros_env, capture_output=True,
                            text=True, timeout=240)
        assert record.exists(), up.stdout + up.stderr
    finally:
        code = stop_recorder(recorder)
    out, err = recorder.communicate()
    assert code == 0, err
    assert "Traceback" not in err, err
    run = json.loads(record.read_text())

    meta = (bag / "metadata.yaml").read_text()
    assert "storage_identifier: mcap" in meta and "version: 9" in meta
    (mcap,) = bag.glob("*.mcap")
    assert mcap.read_bytes()[:8] == MCAP_MAGIC

    messages, types = read_bag(bag)
    states = [msg for _, msg in messages["/fleet/state"] if msg.episode == run["episode"]]
    assert [s.tick for s in states] == list(range(len(run["positions"]))), \
        [s.tick for s in states]
    for state, positions in zip(states, run["positions"]):
        assert [[int(r), int(c)] for r, c in zip(state.rows, state.cols)] == positions, state.tick
    assert states[-1].done and not any(s.done for s in states[:-1])
    # the other fleet topics are there too, with their types
    assert types["/fleet/map"] == "nav_msgs/msg/OccupancyGrid" and len(messages["/fleet/map"]) == 1
    outcomes = [msg for _, msg in messages["/fleet/outcome"] if msg.episode == run["episode"]]
    assert [(o.steps, o.success) for o in outcomes] == [(run["steps"], run["success"])]
    # every robot's move of every tick: the policy processes' batches (RobotMoves)
    moves = [r for _, msg in messages.get("/fleet/move_batches", []) for r in msg.robot_ids]
    moves += [msg.robot_id for _, msg in messages.get("/fleet/moves", [])]
    assert len(moves) == 4 * run["steps"] and types["/fleet/move_batches"].endswith("RobotMoves")
    for robot in range(4):
        assert types[f"/robot_{robot}/pose"] == "geometry_msgs/msg/PoseStamped"
        assert messages[f"/robot_{robot}/pose"], robot
        assert len(messages[f"/robot_{robot}/goal"]) >= 1
    stamps = [stamp for _, stamp_msgs in messages.items() for stamp, _ in stamp_msgs]
    assert abs(min(stamps) / 1e9 - time.time()) < 600  # receive times, system clock


def test_default_topics_are_the_fleets_in_its_namespace():
    from mapf_fleet.ros.bag import default_topic_re

    plain, named = default_topic_re(), default_topic_re("/fleet_a")
    for topic in ("/fleet/map", "/fleet/state", "/fleet/moves", "/fleet/move_batches",
                  "/fleet/progress",
                  "/fleet/outcome", "/robot_0/pose", "/robot_12/goal", "/robot_3/waypoint"):
        assert plain.fullmatch(topic) and not named.fullmatch(topic), topic
        assert named.fullmatch("/fleet_a" + topic) and not plain.fullmatch("/fleet_a" + topic)
    for topic in ("/fleet/markers", "/fleet/robot_status", "/fleet/dhc/hidden", "/robot_x/pose",
                  "/rosout", "/fleet_b/fleet/map"):
        assert not plain.fullmatch(topic) and not named.fullmatch(topic), topic
    command = recorder_command("b", namespace="/fleet_a")
    assert command[-3:] == ["b", "--namespace", "/fleet_a"]


def _line_within(proc, seconds: float) -> str:
    """The recorder's next stdout line, or "" when none comes within `seconds`."""
    import select

    ready, _, _ = select.select([proc.stdout], [], [], seconds)
    return proc.stdout.readline() if ready else ""


@pytest.mark.ros
@pytest.mark.parametrize("repeat", range(2))
def test_the_outcome_is_announced_once_the_final_state_is_written_too(tmp_path, ros_env,
                                                                     rclpy_context, repeat):
    """The outcome follows the final state (`done`) on another topic and can arrive first (CI:
    `up --bag` stopped the recorder on the outcome, and the bag lacked the last 3 ticks). The
    recorder announces the outcome (what `up` waits for before it stops it) only once the final
    state is written too: here the outcome comes first, then a state that is not the last, then
    the last one."""
    from mapf_fleet.ros import common
    from mapf_fleet.ros.bag import OUTCOME_PREFIX
    from mapf_fleet_interfaces.msg import FleetOutcome, FleetState

    rclpy = rclpy_context
    bag = tmp_path / "bag"
    proc = start_recorder(bag, ros_env, topics=["/fleet/state", "/fleet/outcome"])
    node = rclpy.create_node("fleet_stand_in")
    try:
        state = node.create_publisher(FleetState, "/fleet/state", common.reliable_qos(10))
        outcome = node.create_publisher(FleetOutcome, "/fleet/outcome", common.latched_qos(1))
        deadline = time.monotonic() + 60
        while state.get_subscription_count() < 1 or outcome.get_subscription_count() < 1:
            assert time.monotonic() < deadline, "the recorder never matched the publishers"
            rclpy.spin_once(node, timeout_sec=0.1)
        outcome.publish(FleetOutcome(episode=7, steps=1, summary="stand-in"))
        assert _line_within(proc, 1.5) == ""  # the outcome alone: not announced
        state.publish(FleetState(episode=7, tick=0, done=False))
        assert _line_within(proc, 1.5) == ""  # a state that is not the last: still not
        state.publish(FleetState(episode=7, tick=1, done=True))
        line = _line_within(proc, 30)
        assert line.startswith(OUTCOME_PREFIX), (line, proc.stderr.read())
    finally:
        node.destroy_node()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    messages, _ = read_bag(bag)
    assert [m.tick for _, m in messages["/fleet/state"]] == [0, 1]
    assert [m.steps for _, m in messages["/fleet/outcome"]] == [1]
