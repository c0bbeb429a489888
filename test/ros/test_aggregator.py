"""Real-robot mode: the aggregator builds the fleet state from stand-in robots' pose feeds (they
move to their commanded waypoints after random delays); one robot reports an off-grid pose,
which is rejected with a clear log line while that robot holds its cell."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mapf_fleet.grid.actions import ACTION_DELTAS

REPO = Path(__file__).resolve().parents[2]
INSTANCE = REPO / "config" / "fleet" / "instance_small.yaml"
RUN = [sys.executable, "-m", "mapf_fleet.ros.run"]


@pytest.mark.ros
@pytest.mark.slow
def test_aggregator_follows_stand_in_robots_and_rejects_off_grid(tmp_path, ros_env, checkpoints):
    from mapf_fleet.ros.instances import load_instance_yaml

    instance = load_instance_yaml(INSTANCE)
    record = tmp_path / "real.json"
    off_grid, steps = 2, 8
    # ros_env (test/conftest.py) sets ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and ROS_DOMAIN_ID
    robots = subprocess.Popen(
        [sys.executable, "-m", "mapf_fleet.ros.stand_in_robot", "--instance", str(INSTANCE),
         "--max-delay", "0.3", "--off-grid", str(off_grid), "--seed", "1"],
        env=ros_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    policies = subprocess.Popen(
        RUN + ["policy", "--robots", "0-3", "--ros-args", "-p",
               f"checkpoint:={checkpoints['dhc']}", "-p", "comm_timeout:=2.0"],
        env=ros_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        aggregator = subprocess.run(
            RUN + ["aggregator", "--ros-args", "-p", f"instance_file:={INSTANCE}",
                   "-p", f"max_steps:={steps}", "-p", "arrival_timeout:=5.0",
                   "-p", "startup_timeout:=60.0", "-p", f"record_file:={record}"],
            env=ros_env, capture_output=True, text=True, timeout=180)
    finally:
        for proc in (robots, policies):
            proc.kill()
            proc.wait()
    log = aggregator.stdout + aggregator.stderr
    assert record.exists(), log
    run = json.loads(record.read_text())
    assert run["steps"] == steps and run["missed_decisions"] == 0, log
    positions = np.asarray(run["positions"])
    actions = np.asarray(run["actions"])
    np.testing.assert_array_equal(positions[0], instance.starts)  # starts from the pose feeds
    grid = np.asarray(instance.grid)
    off_grid_moves = 0
    for t in range(steps):
        for i in range(4):
            target = positions[t, i] + ACTION_DELTAS[actions[t, i]]
            inside = (0 <= target).all() and (target < grid.shape).all()
            free = inside and not grid[tuple(target)]
            if i == off_grid:
                # every pose it reports after a move is off the grid: it holds its cell
                off_grid_moves += int(actions[t, i] != 0)
                expected = positions[t, i]
            else:
                # the robot went to its waypoint; an obstacle or off-map waypoint is rejected
                expected = target if free else positions[t, i]
            np.testing.assert_array_equal(positions[t + 1, i], expected, f"tick {t} robot {i}")
    # the off-grid robot held its start cell while reporting off-grid poses, and it was named
    assert off_grid_moves > 0, "the off-grid robot never moved: nothing was rejected"
    assert (positions[:, off_grid] == positions[0, off_grid]).all()
    assert any(off_grid in r for r in run["rejected"])
    assert f"robot {off_grid}: pose rejected" in log and "off the 8x8 grid" in log, log
