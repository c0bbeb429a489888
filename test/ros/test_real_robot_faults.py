"""Defects a new user hit in real-robot mode and with a dead simulator:

- every pose feed goes silent: each robot is reported once by id and held; when all are
  silent the run ends with a clear outcome (it went on at one tick per arrival_timeout);
- stand-ins for only some robots: progress while waiting, one line at the end, exit 2, no
  traceback;
- a simulator killed with -9: the record keeps the ticks run, marked incomplete;
- Ctrl-C during start-up: no positions of -1, "stopped at tick 0 while waiting for poses";
- every rejected pose message is counted, also when a good pose follows within the tick.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
INSTANCE = REPO / "config" / "fleet" / "instance_small.yaml"
UP = [sys.executable, "-m", "mapf_fleet.cli", "up"]
STAND_IN = [sys.executable, "-m", "mapf_fleet.ros.stand_in_robot"]
# every process these tests start gets `ros_env` (test/conftest.py): its own ROS_DOMAIN_ID and
# ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, so nothing leaves loopback


def _pose(x, y):
    from geometry_msgs.msg import PoseStamped

    msg = PoseStamped()
    msg.pose.position.x, msg.pose.position.y = float(x), float(y)
    return msg


@pytest.mark.ros
def test_every_rejected_pose_is_counted_even_when_a_good_one_follows(rclpy_context):
    from rclpy.parameter import Parameter

    from mapf_fleet.ros.aggregator_node import FleetStateAggregator

    node = FleetStateAggregator(parameter_overrides=[
        Parameter("instance_file", value=str(INSTANCE))])
    try:
        cell = node.geometry.cell_to_xy
        node._on_pose(0, _pose(*cell(0, 0)))
        node._on_pose(0, _pose(*cell(2, 0)))   # a jump: rejected ...
        node._on_pose(0, _pose(*cell(1, 0)))   # ... and a good pose before the tick ends
        assert node._rejected_reason == {}      # nothing is rejected now
        assert node.rejected == 1               # but the rejection counts
        assert node._rejected_in_tick == {0}    # and the tick's record will name robot 0
    finally:
        node.destroy_node()


@pytest.mark.ros
def test_a_silent_robot_is_reported_once_and_all_silent_ends_the_run(rclpy_context, capfd):
    from rclpy.parameter import Parameter

    from mapf_fleet.ros.aggregator_node import FleetStateAggregator

    node = FleetStateAggregator(parameter_overrides=[
        Parameter("instance_file", value=str(INSTANCE)), Parameter("pose_timeout", value=1.0)])
    try:
        now = time.monotonic()
        node._heard = {0: now - 5.0, 1: now, 2: now, 3: now - 5.0}
        capfd.readouterr()
        assert node._check_silent() == [0, 3]
        assert node._check_silent() == [0, 3]   # reported once
        err = capfd.readouterr().err
        assert err.count("no pose for 1.0 s") == 1 and "robots [0, 3]" in err
        node._on_pose(0, _pose(*node.geometry.cell_to_xy(0, 0)))   # its feed comes back
        assert node._check_silent() == [3] and "robot 0: pose feed back" in capfd.readouterr().err
    finally:
        node.destroy_node()


def _wait_for_line(proc, text, timeout):
    """Read `proc`'s stdout until a line contains `text`; all lines read."""
    lines, deadline = [], time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if text in line:
            return lines
    raise AssertionError(f"no line with {text!r}:\n" + "".join(lines[-40:]))


@pytest.mark.ros
@pytest.mark.slow
def test_pose_feeds_that_all_go_silent_end_the_run(tmp_path, ros_env, checkpoints):
    record = tmp_path / "silent.json"
    stand_ins = subprocess.Popen(STAND_IN + ["--instance", str(INSTANCE), "--max-delay", "0.1"],
                                 env=ros_env, stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL)
    up = subprocess.Popen(UP + ["--checkpoint", checkpoints["dcc"], "--instance", str(INSTANCE),
                                "--real-robots", "--nodes-per-process", "2", "--task-source",
                                "lifelong", "--max-steps", "5000", "--record", str(record),
                                "--ros-args", "-p", "pose_timeout:=2.0", "-p",
                                "progress_every:=1"],
                          env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True)
    try:
        lines = _wait_for_line(up, "tick 3:", 240)
        stand_ins.kill()  # kill -9: every feed silent at once
        stand_ins.wait(30)
        out, _ = up.communicate(timeout=180)
    finally:
        for proc in (stand_ins, up):
            if proc.poll() is None:
                proc.kill()
    text = "".join(lines) + out
    assert up.returncode == 1, text[-3000:]
    assert text.count("no pose for 2.0 s") >= 1
    assert "every robot's pose feed is silent" in text
    summary = json.loads(record.read_text())["summary"]
    assert summary.startswith("stopped at tick") and "silent" in summary, summary


@pytest.mark.ros
@pytest.mark.slow
def test_stand_ins_for_only_some_robots_end_in_one_line_and_exit_2(tmp_path, ros_env,
                                                                   checkpoints):
    from mapf_fleet.fleet.instances import dump_instance_yaml, load_instance_yaml

    full = load_instance_yaml(INSTANCE)
    half = type(full)(full.grid, full.starts[:2], full.goals[:2])
    half_path = tmp_path / "half.yaml"
    dump_instance_yaml(half, half_path)
    stand_ins = subprocess.Popen(STAND_IN + ["--instance", str(half_path)], env=ros_env,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        proc = subprocess.run(UP + ["--checkpoint", checkpoints["dcc"], "--instance",
                                    str(INSTANCE), "--real-robots", "--nodes-per-process", "2",
                                    "--startup-timeout", "20"],
                              env=ros_env, capture_output=True, text=True, timeout=300)
    finally:
        stand_ins.send_signal(signal.SIGINT)
        stand_ins.wait(30)
    text = proc.stdout + proc.stderr
    assert proc.returncode == 2, text[-3000:]
    assert "waiting for poses from robots [2, 3]" in text
    assert "no valid pose from robots [2, 3] within startup_timeout 20.0 s" in text
    assert "Traceback" not in text and "no outcome" not in text


@pytest.mark.ros
@pytest.mark.slow
def test_ctrl_c_while_waiting_for_robots_reports_the_wait(tmp_path, ros_env, checkpoints):
    record = tmp_path / "run.json"
    up = subprocess.Popen(UP + ["--checkpoint", checkpoints["dcc"], "--instance", str(INSTANCE),
                                "--real-robots", "--nodes-per-process", "2", "--record",
                                str(record)],
                          env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True)
    try:
        lines = _wait_for_line(up, "waiting for poses from robots", 240)
        up.send_signal(signal.SIGINT)
        out, _ = up.communicate(timeout=120)
    finally:
        if up.poll() is None:
            up.kill()
    text = "".join(lines) + out
    assert up.returncode == 130, text[-3000:]
    assert "posed at [[-1" not in text and "starting without ready robots" not in text
    assert "stopped at tick 0 while waiting for poses from robots [0, 1, 2, 3]" in text


@pytest.mark.ros
@pytest.mark.slow
def test_a_killed_simulator_leaves_the_ticks_it_ran_in_the_record(tmp_path, ros_env,
                                                                 checkpoints):
    import os

    record = tmp_path / "run.json"
    up = subprocess.Popen(UP + ["--checkpoint", checkpoints["dcc"], "--num-robots", "4",
                                "--size", "10", "--task-source", "lifelong", "--max-steps",
                                "5000", "--nodes-per-process", "4", "--record", str(record),
                                "--ros-args", "-p", "progress_every:=5"],
                          env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True)
    try:
        # killed at once: the record was written whole at the first tick only, the journal
        # has every tick since
        _wait_for_line(up, "tick 20:", 240)
        # this run's simulator only (a child of this `up`), never another test's
        sim = subprocess.run(["pgrep", "-P", str(up.pid), "-f", "mapf_fleet.ros.run simulator"],
                             capture_output=True, text=True).stdout.split()
        assert sim, "no simulator process"
        for pid in sim:
            os.kill(int(pid), signal.SIGKILL)
        out, _ = up.communicate(timeout=120)
    finally:
        if up.poll() is None:
            up.kill()
    assert up.returncode == 1, out[-3000:]
    data = json.loads(record.read_text())
    assert data["incomplete"] and data["steps"] >= 20 and len(data["positions"]) > 20
    assert "no outcome" not in out and "incomplete: the run's record stops at tick" in out
