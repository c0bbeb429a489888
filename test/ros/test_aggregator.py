"""Real-robot mode: the aggregator builds the fleet state from stand-in robots' pose feeds (they
move to the waypoints it commands after random delays); one robot reports an off-grid pose,
which is rejected with a clear log line while that robot holds its cell. On a dense map with
slow robots the commands stay safe: never two robots in one cell, on an obstacle, or a jump."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mapf_fleet.coordination.rules import FLEET_RULE
from mapf_fleet.grid.actions import ACTION_DELTAS
from mapf_fleet.fleet.arbiter import unsafe_commands

REPO = Path(__file__).resolve().parents[2]
INSTANCE = REPO / "config" / "fleet" / "instance_small.yaml"
RUN = [sys.executable, "-m", "mapf_fleet.ros.run"]


@pytest.mark.ros
@pytest.mark.slow
def test_aggregator_follows_stand_in_robots_and_rejects_off_grid(tmp_path, ros_env, checkpoints):
    from mapf_fleet.fleet.instances import load_instance_yaml

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
    assert run["conflict_rule"] == FLEET_RULE and run["pose_conflicts"] == 0, log
    positions = np.asarray(run["positions"])
    executed = np.asarray(run["executed"])
    waypoints = np.asarray(run["waypoints"])
    np.testing.assert_array_equal(positions[0], instance.starts)  # starts from the pose feeds
    grid = np.asarray(instance.grid)
    off_grid_moves = 0
    for t in range(steps):
        assert unsafe_commands(grid, positions[t], waypoints[t]) == [], f"tick {t}"
        for i in range(4):
            if i == off_grid:
                # every pose it reports after a move is off the grid: it holds its cell, and is
                # in transit (both cells, its old waypoint kept) from then on
                in_transit = off_grid_moves > 0
                assert (i in run["late"][t]) == in_transit, f"tick {t}"
                if in_transit:
                    assert executed[t, i] == 0 and (waypoints[t, i] != positions[t, i]).any()
                off_grid_moves += int(executed[t, i] != 0)
                np.testing.assert_array_equal(positions[t + 1, i], positions[t, i])
            else:
                # the robot went to its commanded cell: the executed move from its cell
                target = positions[t, i] + ACTION_DELTAS[executed[t, i]]
                np.testing.assert_array_equal(waypoints[t, i], target, f"tick {t} robot {i}")
                np.testing.assert_array_equal(positions[t + 1, i], target, f"tick {t} robot {i}")
    # the off-grid robot held its start cell while reporting off-grid poses, and it was named
    assert off_grid_moves > 0, "the off-grid robot never moved: nothing was rejected"
    assert (positions[:, off_grid] == positions[0, off_grid]).all()
    assert any(off_grid in r for r in run["rejected"])
    assert any(off_grid in late for late in run["late"])
    assert f"robot {off_grid}: pose rejected" in log and "off the 8x8 grid" in log, log


def _start(command, env, log_path) -> subprocess.Popen:
    """`command` with its output (stdout and stderr) in `log_path`."""
    with open(log_path, "w") as out:
        return subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT)


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("rule, num_robots", [("pibt", 24), ("revert", 16)])
def test_dense_map_slow_robots_never_collide(tmp_path, ros_env, checkpoints, rule, num_robots):
    """16x16, density 0.3, stand-in robots that take up to 0.6 s per move against an arrival
    timeout of 0.3 s, so robots are often still on their way at the next tick (they hold both
    cells) and followers wait for their cell to be vacated. The recorded poses never show two
    robots in one cell, a robot on an obstacle or a jump; the run ends with an outcome."""
    from mapf_fleet.grid.instance import generate_instance
    from mapf_fleet.fleet.instances import dump_instance_yaml

    instance = generate_instance(16, num_robots, 0.3, 21)
    path = tmp_path / "dense.yaml"
    dump_instance_yaml(instance, path)
    record = tmp_path / "dense.json"
    steps = 25
    # the robots' and policy processes' output is kept: a failure shows it with the aggregator's
    logs = {"stand-in robots": tmp_path / "robots.log"}
    logs.update({f"policy {first}": tmp_path / f"policy_{first}.log"
                 for first in range(0, num_robots, 8)})
    procs = [_start([sys.executable, "-m", "mapf_fleet.ros.stand_in_robot", "--instance",
                     str(path), "--max-delay", "0.6", "--seed", "3"],
                    ros_env, logs["stand-in robots"])]
    for first in range(0, num_robots, 8):
        ids = f"{first}-{min(first + 8, num_robots) - 1}"
        procs.append(_start(RUN + ["policy", "--robots", ids, "--ros-args",
                                   "-p", f"checkpoint:={checkpoints['dhc']}",
                                   "-p", "comm_timeout:=3.0"],
                            ros_env, logs[f"policy {first}"]))
    try:
        aggregator = subprocess.run(
            RUN + ["aggregator", "--ros-args", "-p", f"instance_file:={path}",
                   "-p", f"max_steps:={steps}", "-p", "arrival_timeout:=0.3",
                   "-p", f"conflict_rule:={rule}", "-p", "decision_timeout:=10.0",
                   "-p", "startup_timeout:=120.0", "-p", f"record_file:={record}"],
            env=ros_env, capture_output=True, text=True, timeout=420)
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()
    log = aggregator.stdout + aggregator.stderr + "".join(
        f"\n--- {name} (last lines) ---\n" + "\n".join(file.read_text().splitlines()[-20:])
        for name, file in logs.items())
    assert record.exists(), log
    run = json.loads(record.read_text())
    assert run["success"] or run["steps"] == steps, log   # an outcome
    assert run["conflict_rule"] == rule
    assert run["pose_conflicts"] == 0, log                 # never two robots reported in a cell
    assert run["collisions"] == 0 and not any(run["rejected"]), log
    grid = np.asarray(instance.grid)
    positions = np.asarray(run["positions"])
    np.testing.assert_array_equal(positions[0], instance.starts)
    for t, cells in enumerate(positions):
        assert len({tuple(c) for c in cells}) == num_robots, f"two robots in one cell at {t}"
        assert not grid[cells[:, 0], cells[:, 1]].any(), f"a robot on an obstacle at {t}"
        if t:
            jump = np.abs(cells - positions[t - 1]).sum(axis=1)
            assert jump.max() <= 1, f"a robot moved {jump.max()} cells at tick {t}"
    for t, commanded in enumerate(run["waypoints"]):
        assert unsafe_commands(grid, positions[t], commanded) == [], f"tick {t}"
    # the slow robots were really still driving at some ticks, and the fleet did move
    assert sum(map(len, run["late"])) > 0, log
    moved = int((positions[-1] != positions[0]).any(axis=1).sum())
    assert moved >= num_robots // 4, f"{moved} robots moved: {run['summary']}\n{log}"
