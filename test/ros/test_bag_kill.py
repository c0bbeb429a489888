"""A killed `mapf-fleet record` keeps its bag up to the last tick (issue 40, item 3): the
recorder writes each tick to the file as it ends (rosbags' MCAP writer would keep 1 MiB in
memory), and `render --run` reads a bag without metadata.yaml or MCAP summary, saying so and that
the bag ends without the run's outcome."""

# Loopback only: every ROS process these tests start runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
# and its own ROS_DOMAIN_ID (test/conftest.py, ros_env / _isolate_ros_tests).

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from mapf_fleet.ros.bag import READY_PREFIX, recorder_command

TICKS = 12


@pytest.mark.ros
def test_a_bag_killed_with_sigkill_keeps_every_tick_but_the_last(tmp_path, ros_env,
                                                                  rclpy_context):
    from mapf_fleet_interfaces.msg import FleetProgress, FleetState
    from nav_msgs.msg import OccupancyGrid

    from mapf_fleet.fleet.topics import MapGeometry
    from mapf_fleet.ros import common

    rclpy = rclpy_context
    bag = tmp_path / "bag"
    proc = subprocess.Popen(recorder_command(bag), env=ros_env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    node = rclpy.create_node("fake_fleet")
    try:
        line = proc.stdout.readline()
        assert line.startswith(READY_PREFIX), (line, proc.stderr.read())
        grid = np.zeros((6, 6), dtype=np.uint8)
        map_pub = node.create_publisher(OccupancyGrid, common.MAP_TOPIC, common.latched_qos())
        map_pub.publish(common.grid_to_occupancy(grid, MapGeometry()))
        state_pub = node.create_publisher(FleetState, common.STATE_TOPIC, common.reliable_qos(10))
        progress_pub = node.create_publisher(FleetProgress, common.PROGRESS_TOPIC,
                                             common.reliable_qos(10))
        deadline = time.monotonic() + 60
        while state_pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert state_pub.get_subscription_count() > 0, "the recorder never subscribed"
        time.sleep(1.0)  # the recorder matches the latched map too
        for tick in range(TICKS):
            progress_pub.publish(FleetProgress(episode=7, tick=tick, num_robots=2,
                                               goals_reached=tick // 3))
            state_pub.publish(FleetState(episode=7, tick=tick, rows=[0, 5], cols=[tick % 6, 1],
                                         goal_rows=[0, 5], goal_cols=[5, 5]))
            time.sleep(0.1)
        mcap = next(bag.glob("*.mcap"))
        deadline = time.monotonic() + 10
        while mcap.stat().st_size == 0 and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(0.5)
        assert mcap.stat().st_size > 0, "the ticks stayed in the recorder's memory"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
        node.destroy_node()
    assert not (bag / "metadata.yaml").exists()  # killed: never closed
    out = tmp_path / "frames"
    done = subprocess.run([sys.executable, "-m", "mapf_fleet.cli", "render", "--run", str(bag),
                           "--out", str(out)], env=ros_env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    assert "the bag was not closed" in done.stderr
    assert f"ends at tick {TICKS - 1} without the run's outcome" in done.stderr \
        or f"ends at tick {TICKS - 2} without the run's outcome" in done.stderr, done.stderr
    assert len(list(out.glob("frame_*.png"))) >= TICKS - 1  # at most the last tick lost


@pytest.mark.ros
@pytest.mark.slow
def test_kill_9_of_up_bag_keeps_the_last_tick_and_the_outcome(tmp_path, ros_env, checkpoints):
    """`up` killed with SIGKILL: its children get SIGTERM (PR_SET_PDEATHSIG); the recorder,
    seeing `up` gone, waits for the stopped simulator's outcome before it closes the bag."""
    bag, record = tmp_path / "bag", tmp_path / "run.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "mapf_fleet.cli", "up", "--checkpoint", checkpoints["dhc"],
         "--num-robots", "2", "--size", "8", "--max-steps", "500", "--task-source", "lifelong",
         "--nodes-per-process", "2",
         "--record", str(record), "--bag", str(bag), "--ros-args", "-p", "tick_period:=0.2",
         "-p", "progress_every:=2"],
        env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        for line in proc.stdout:
            if "tick 6:" in line:
                break
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    deadline = time.monotonic() + 60  # the recorder closes the bag on its own
    while not (bag / "metadata.yaml").exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert (bag / "metadata.yaml").exists(), "the recorder did not close the bag"
    from rosbags.rosbag2 import Reader

    from mapf_fleet.fleet.record import read_record
    from mapf_fleet.ros.bag import fleet_typestore

    typestore = fleet_typestore()
    with Reader(bag) as reader:
        got = [(c.topic, typestore.deserialize_cdr(raw, c.msgtype))
               for c, _, raw in reader.messages() if c.topic in ("/fleet/state", "/fleet/outcome")]
    outcomes = [m for topic, m in got if topic == "/fleet/outcome"]
    assert outcomes and outcomes[-1].summary.startswith("stopped at tick"), "no outcome"
    last = max(m.tick for topic, m in got if topic == "/fleet/state")
    assert last == len(read_record(record)["positions"]) - 1  # the last tick is in
