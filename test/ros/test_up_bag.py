"""The bag, the launcher's side: `mapf-fleet up --bag DIR` runs the rosbag2 recorder
(`mapf-fleet record`, mapf_fleet/ros/bag.py) beside the fleet and closes the bag when the fleet
ends, also when `up` is stopped by Ctrl-C; the bag's states are the JSON record's."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import pytest

UP = [sys.executable, "-m", "mapf_fleet.cli", "up"]


def test_up_refuses_an_existing_bag_directory_before_anything_starts(tmp_path):
    from mapf_fleet.ros.launcher import main

    assert main(["--bag", str(tmp_path), "--num-robots", "2", "--size", "8"]) == 2


@pytest.mark.ros
@pytest.mark.slow
def test_up_bag_records_the_fleet_and_closes_the_bag_on_ctrl_c(tmp_path, ros_env, checkpoints):
    from rosbags.rosbag2 import Reader

    from mapf_fleet.ros.bag import fleet_typestore

    bag, record = tmp_path / "bag", tmp_path / "run.json"
    # ros_env (test/conftest.py): ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, own domain
    assert ros_env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    proc = subprocess.Popen(
        UP + ["--checkpoint", checkpoints["dhc"], "--num-robots", "4", "--size", "10",
              "--max-steps", "500", "--nodes-per-process", "2", "--record", str(record),
              "--bag", str(bag), "--ros-args", "-p", "tick_period:=0.2", "-p",
              "progress_every:=2"],
        env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out = []
    try:
        for line in proc.stdout:
            out.append(line)
            if "tick 6:" in line:
                break
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = "".join(out) + rest
    assert proc.returncode == 130, text
    assert "mapf-fleet record: wrote" in text and "Traceback" not in text, text
    assert (bag / "metadata.yaml").exists(), text  # closed
    run = json.loads(record.read_text())
    typestore = fleet_typestore()
    with Reader(bag) as reader:
        states = [typestore.deserialize_cdr(raw, c.msgtype)
                  for c, _, raw in reader.messages() if c.topic == "/fleet/state"]
    states = [s for s in states if s.episode == run["episode"]]
    # a stop that comes while a tick's moves are collected ends the run at that tick: its state
    # went out (not done) and goes out again marked done; each tick counts once, the last kept
    states = [s for k, s in enumerate(states)
              if k + 1 == len(states) or states[k + 1].tick != s.tick]
    assert [s.tick for s in states] == list(range(len(run["positions"]))), text
    for state, positions in zip(states, run["positions"]):
        assert [[int(r), int(c)] for r, c in zip(state.rows, state.cols)] == positions
    assert states[-1].done and run["summary"].startswith("stopped at tick")
