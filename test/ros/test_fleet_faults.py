"""Faults over ROS: a killed policy node leaves its robot standing (reported, the run goes on),
and a restarted node rejoins at the current tick."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time

import pytest

RUN = [sys.executable, "-m", "mapf_fleet.ros.run"]


def _policy(env, checkpoint, robot_id):
    # env is ros_env (test/conftest.py): ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, own domain
    return subprocess.Popen(RUN + ["policy", "--ros-args", "-p", f"robot_id:={robot_id}",
                                   "-p", f"checkpoint:={checkpoint}", "-p", "comm_timeout:=0.3"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


@pytest.mark.ros
@pytest.mark.slow
def test_killed_node_stands_and_restarted_node_rejoins(tmp_path, ros_env, checkpoints):
    record = tmp_path / "run.json"
    num_robots, max_steps = 4, 45
    policies = {i: _policy(ros_env, checkpoints["dhc"], i) for i in range(num_robots)}
    # ros_env (test/conftest.py) sets ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and ROS_DOMAIN_ID
    simulator = subprocess.Popen(
        RUN + ["simulator", "--ros-args", "-p", f"num_robots:={num_robots}", "-p", "size:=10",
               "-p", "seed:=4", "-p", f"max_steps:={max_steps}", "-p", "decision_timeout:=1.5",
               "-p", "tick_period:=0.25", "-p", "progress_every:=1",
               "-p", f"record_file:={record}"],
        env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    killed_at = restarted_at = None
    try:
        for line in simulator.stdout:
            match = re.search(r"tick (\d+): \d+/", line)
            if not match:
                continue
            tick = int(match.group(1))
            if killed_at is None and tick >= 5:
                policies[1].kill()
                policies[1].wait()
                killed_at = tick
            elif killed_at is not None and restarted_at is None and tick >= killed_at + 6:
                policies[1] = _policy(ros_env, checkpoints["dhc"], 1)
                restarted_at = tick
        assert simulator.wait(timeout=60) in (0, 1)
    finally:
        for proc in list(policies.values()) + [simulator]:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    run = json.loads(record.read_text())
    assert killed_at is not None and restarted_at is not None
    assert run["steps"] == len(run["actions"]) > restarted_at   # the run went on to its end
    missed_ticks = [t for t, missing in enumerate(run["missed"]) if 1 in missing]
    assert missed_ticks, "the killed robot's missing decisions were not reported"
    assert run["missed_decisions"] >= len(missed_ticks)
    assert "robots [1]" in run["summary"]
    for t in missed_ticks:
        assert run["actions"][t][1] == 0                            # it stood still
        assert run["positions"][t + 1][1] == run["positions"][t][1]
    # the other robots never missed a decision
    assert all(set(m) <= {1} for m in run["missed"])
    # rejoined: robot 1 decides again in the last ticks (the restart takes a few seconds)
    assert 1 not in run["missed"][-1], f"robot 1 did not rejoin (missed at {missed_ticks})"
