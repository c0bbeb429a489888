"""`mapf-fleet up` parameter precedence as `ros2 launch` users expect: command line > params file
> `up`'s own defaults, and `up --ros-args ...` passed on to every node (issue 17 item 6)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from mapf_fleet.ros import params as rp

CLI = [sys.executable, "-m", "mapf_fleet.cli"]


def test_params_file_node_keys_and_rules(tmp_path):
    for key, fqn, expected in [("/**", "/mapf_simulator", True), ("/**", "/a/b", True),
                               ("mapf_simulator", "/mapf_simulator", True),
                               ("/mapf_simulator", "/fleet_a/mapf_simulator", False),
                               ("/**/mapf_simulator", "/fleet_a/mapf_simulator", True),
                               ("/fleet_a/mapf_policy_*", "/fleet_a/mapf_policy_3", True),
                               ("/fleet_a/mapf_policy_*", "/fleet_b/mapf_policy_3", False)]:
        assert rp.key_matches(key, fqn) is expected, (key, fqn)
    path = tmp_path / "p.yaml"
    path.write_text("fleet_a:\n  mapf_simulator:\n    ros__parameters:\n      size: 9\n"
                    "      nested: {x: 1}\n/**:\n  ros__parameters:\n    size: 7\n    seed: 2\n")
    assert rp.params_file_values([path], "/fleet_a/mapf_simulator") == {
        "size": 7, "nested.x": 1, "seed": 2}
    assert rp.params_file_values([path], "/mapf_simulator") == {"size": 7, "seed": 2}
    rules, files, ns = rp.ros_arg_rules(["--ros-args", "-p", "size:=5", "-p",
                                         "mapf_policy_0:checkpoint:=a.pt", "--params-file", "q",
                                         "-r", "__ns:=/x"])
    assert rules == [("", "size", 5), ("mapf_policy_0", "checkpoint", "a.pt")]
    assert (files, ns) == (["q"], "/x")
    with pytest.raises(FileNotFoundError, match="params file not found"):
        rp.read_params_file(tmp_path / "missing.yaml")


def _plan(argv):
    from mapf_fleet.ros import common, launcher

    own, ros_args = common.split_ros_args(argv)
    args = launcher.build_parser().parse_args(own)
    launcher.apply_parameter_sources(own, args, ros_args)
    return args


def test_precedence_command_line_over_file_over_defaults(tmp_path):
    from mapf_fleet.ros.launcher import _ros_args

    path = tmp_path / "p.yaml"
    path.write_text("mapf_simulator:\n  ros__parameters:\n    num_robots: 4\n    size: 12\n"
                    "/**:\n  ros__parameters:\n    comm_timeout: 0.7\n")
    args = _plan(["--params-file", str(path)])
    assert (args.num_robots, args.size, args.comm_timeout, args.seed) == (4, 12, 0.7, 0)
    sim = _ros_args({"num_robots": 4, "size": 12, "seed": 0}, args, "sim")
    # the file's values are not overridden by up's defaults; defaults the file lacks are passed
    assert sim == ["--ros-args", "--params-file", str(path), "-p", "seed:=0"]
    args = _plan(["--params-file", str(path), "--num-robots", "6", "--ros-args", "-p",
                  "size:=10"])
    assert (args.num_robots, args.size) == (6, 10)
    sim = _ros_args({"num_robots": 6, "size": 10}, args, "sim")
    assert sim[-3:] == ["--ros-args", "-p", "size:=10"]  # the user's --ros-args come last
    assert sim.index("--params-file") < sim.index("num_robots:=6")  # the file first: later wins
    with pytest.raises(ValueError, match="parameter num_robots: expected int, got 'abc'"):
        _plan(["--ros-args", "-p", "num_robots:=abc"])


def _up(tmp_path, env, *args):
    # env is ros_env (test/conftest.py): ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, own domain
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    record = tmp_path / "run.json"
    done = subprocess.run(CLI + ["up", "--record", str(record), *args], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode in (0, 1), done.stdout + done.stderr
    assert record.is_file(), done.stdout + done.stderr
    return done.stdout + done.stderr, json.loads(record.read_text())


@pytest.mark.ros
@pytest.mark.slow
def test_up_params_file_and_ros_args(tmp_path, ros_env, checkpoints):
    from mapf_fleet.grid.instance import generate_instance

    path = tmp_path / "fleet.yaml"
    path.write_text("mapf_simulator:\n  ros__parameters:\n    num_robots: 4\n    size: 12\n"
                    "    max_steps: 2\n    decision_timeout: 3.0\n")
    out, run = _up(tmp_path, ros_env, "--checkpoint", checkpoints["dhc"], "--single-process",
                   "--params-file", str(path))
    assert "instance 12x12 with 4 robots" in out, out  # was 16x16 with 8 robots
    assert np.asarray(run["positions"]).shape[1:] == (4, 2) and run["steps"] == 2
    # the command line beats the file; --ros-args reaches the nodes
    out, run = _up(tmp_path, ros_env, "--checkpoint", checkpoints["dhc"], "--single-process",
                   "--params-file", str(path), "--num-robots", "3", "--ros-args", "-p", "seed:=5")
    assert "instance 12x12 with 3 robots" in out, out
    expected = generate_instance(12, 3, 0.3, 5)
    assert run["positions"][0] == np.asarray(expected.starts).tolist()
    # separate processes: the same precedence
    out, run = _up(tmp_path, ros_env, "--checkpoint", checkpoints["dhc"],
                   "--nodes-per-process", "2", "--params-file", str(path), "--num-robots", "2")
    assert "instance 12x12 with 2 robots" in out, out
    assert np.asarray(run["positions"]).shape[1:] == (2, 2) and run["steps"] == 2
