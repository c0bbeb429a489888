"""The fleet's parameters have one truth (mapf_fleet.fleet.parameters: one table per node kind):
the nodes declare them from it, `mapf-fleet up` takes its defaults and checks from it and hands
every node one merged params file (table defaults < params file < options < -p), and
config/fleet/fleet.yaml agrees with it. Every bad value is refused by `up` before anything
starts, with one line naming the option or file, the field and the value."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from mapf_fleet.ros import launcher
from mapf_fleet.fleet import parameters as P

CLI = [sys.executable, "-m", "mapf_fleet.cli"]
REPO = Path(__file__).resolve().parents[2]


def test_the_table_module_and_up_import_no_rclpy():
    code = ("import sys, mapf_fleet.fleet.parameters, mapf_fleet.ros.launcher; "
            "print('rclpy' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert done.stdout.strip() == "False", done.stdout + done.stderr


def test_fleet_yaml_and_up_help_agree_with_the_tables():
    data = yaml.safe_load((REPO / "config/fleet/fleet.yaml").read_text())
    for key, entry in data.items():
        values = entry["ros__parameters"]
        tables = ([P.SIMULATOR, P.AGGREGATOR, P.POLICY] if key == "/**"
                  else [P.table_of(key)])
        for name, value in values.items():
            table = next((t for t in tables if name in t), None)
            assert table is not None, f"fleet.yaml {key}: {name} is no parameter"
            if key != "/**" or table is P.POLICY:
                assert value == table[name].default, (key, name, value, table[name].default)
    shown = " ".join(launcher.build_parser().format_help().split())
    for option, name in [("--decision-timeout", "decision_timeout"),
                         ("--startup-timeout", "startup_timeout"), ("--size", "size"),
                         ("--density", "density"), ("--seed", "seed")]:
        default = P.SIMULATOR[name].default
        assert f"(default: {default})" in shown.split(option, 2)[2][:400], option
    assert f"(default: {P.POLICY['comm_timeout'].default})" in shown
    # the aggregator's and the simulator's shared parameters have the same defaults
    for name in set(P.SIMULATOR) & set(P.AGGREGATOR):
        assert P.SIMULATOR[name].default == P.AGGREGATOR[name].default, name


def _prepare(argv, checkpoint):
    args, plan, robots = launcher.prepare(["--checkpoint", checkpoint] + list(argv))
    return args, plan, robots


def test_precedence_defaults_file_options_command_line(tmp_path, checkpoints):
    path = tmp_path / "p.yaml"
    path.write_text("mapf_simulator:\n  ros__parameters:\n    num_robots: 4\n    size: 12\n"
                    "    decision_timeout: 3\n"
                    "/**:\n  ros__parameters:\n    comm_timeout: 0.7\n"
                    "mapf_policy_1:\n  ros__parameters:\n    comm_timeout: 0.9\n")
    args, plan, robots = _prepare(["--params-file", str(path)], checkpoints["dhc"])
    assert (plan.sim["num_robots"], plan.sim["size"], plan.sim["seed"]) == (4, 12, 0)
    assert plan.sim["decision_timeout"] == 3.0 and isinstance(plan.sim["decision_timeout"],
                                                              float)
    assert plan.values["mapf_policy_0"]["comm_timeout"] == 0.7
    assert plan.values["mapf_policy_1"]["comm_timeout"] == 0.9
    assert plan.sim["startup_timeout"] == P.SIMULATOR["startup_timeout"].default
    args, plan, robots = _prepare(["--params-file", str(path), "--num-robots", "6",
                                   "--comm-timeout", "1.5", "--ros-args", "-p", "size:=10",
                                   "-p", "num_robots:=5"], checkpoints["dhc"])
    assert (plan.sim["num_robots"], plan.sim["size"], robots) == (5, 10, 5)  # -p beats options
    assert plan.values["mapf_policy_1"]["comm_timeout"] == 1.5  # the option beats the file
    assert plan.values["mapf_policy_4"]["conflict_rule"] == plan.sim["conflict_rule"]
    # one params file for every node, fully resolved, keyed by the node's full name
    out = tmp_path / "merged.yaml"
    P.write_params_file(out, plan.values, "/fleet_a")
    merged = yaml.safe_load(out.read_text())
    assert set(merged) == {"/fleet_a/mapf_simulator"} | {f"/fleet_a/mapf_policy_{i}"
                                                          for i in range(5)}
    assert merged["/fleet_a/mapf_simulator"]["ros__parameters"]["size"] == 10
    assert "robot_id" not in merged["/fleet_a/mapf_policy_2"]["ros__parameters"]
    # external goals: no tick limit unless one is given
    _, plan, _ = _prepare(["--task-source", "external"], checkpoints["dhc"])
    assert plan.sim["max_steps"] == 0


def test_a_large_fleet_leaves_out_the_per_robot_action_servers_unless_asked(checkpoints):
    """From 256 robots `up` gives the simulator robot_actions false (one line says so and how to
    keep them); below, or set by the user in any way, the value stands."""
    size = ["--size", "40", "--nodes-per-process", "32"]
    _, plan, _ = _prepare(["--num-robots", "256"] + size, checkpoints["dcc"])
    assert plan.sim["robot_actions"] is False
    notes = [w for w in plan.warnings if "robot_actions" in w]
    assert len(notes) == 1 and "fleet/navigate_to_pose" in notes[0] and "\n" not in notes[0]
    _, plan, _ = _prepare(["--num-robots", "255"] + size, checkpoints["dcc"])
    assert plan.sim["robot_actions"] is True
    assert not [w for w in plan.warnings if "robot_actions" in w]
    for given in (["--ros-args", "-p", "robot_actions:=true"],
                  ["--ros-args", "-p", "mapf_simulator:robot_actions:=true"]):
        _, plan, _ = _prepare(["--num-robots", "256"] + size + given, checkpoints["dcc"])
        assert plan.sim["robot_actions"] is True, given


def test_preference_mode_is_a_deprecated_alias_of_ranking(tmp_path, checkpoints, capsys):
    path = tmp_path / "old.yaml"
    path.write_text("/**:\n  ros__parameters:\n    preference_mode: distance\n")
    _, plan, _ = _prepare(["--params-file", str(path)], checkpoints["dhc"])
    assert plan.policy["ranking"] == "distance" and "preference_mode" not in plan.policy
    assert any("preference_mode is deprecated, use ranking" in w for w in plan.warnings)
    args, plan, _ = _prepare(["--preference-mode", "q"], checkpoints["dhc"])
    assert plan.policy["ranking"] == "q"
    assert "--preference-mode is deprecated" in capsys.readouterr().err
    _, plan, _ = _prepare(["--ranking", "q_demote_stay"], checkpoints["dhc"])
    assert plan.policy["ranking"] == "q_demote_stay"


def _bad(tmp_path):
    (tmp_path / "afile").write_text("x")
    (tmp_path / "unknown.yaml").write_text("mapf_simulator:\n  ros__parameters:\n"
                                           "    num_robotz: 3\n")
    (tmp_path / "bad_value.yaml").write_text("/**:\n  ros__parameters:\n"
                                             "    decision_timeout: -1.0\n")
    (tmp_path / "room.map").write_text("type octile\nheight 3\nwidth 4\nmap\n....\n.@..\n"
                                       "....\n")
    (tmp_path / "b.yaml").write_text("image: b.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n")
    (tmp_path / "i.yaml").write_text('grid: ["...."]\nstarts: [[0, 0]]\ngoals: [[0, 3]]\n')
    d = tmp_path
    return [  # (argv, what the one line must say)
        (["--record", f"{d}/afile/run.json"], f"--record {d}/afile/run.json: folder"),
        (["--record", str(d)], "is a directory"),
        (["--record", "/proc/run.json"], "--record /proc/run.json: cannot write"),
        (["--real-robots", "--origin", "nan", "0"], "--origin: origin_x must be a finite"),
        (["--ros-args", "-p", "conflict_rule:=bogus"],
         "-p conflict_rule:=bogus: conflict_rule must be one of"),
        (["--ros-args", "-p", "task_source:=bogus"], "task_source must be one of"),
        (["--namespace", "bad name"], "--namespace must be a ROS namespace"),
        (["--namespace", "/9fleet"], "--namespace must be a ROS namespace"),
        (["--ros-args", "-p", "seed:=1", "--num-robots", "4"],
         "--num-robots is an option of `mapf-fleet up`: put it before --ros-args"),
        (["--ros-args", "--bogus"], "unknown ROS argument '--bogus'"),
        (["--ros-args", "-p", "num_robotz:=3"], "-p num_robotz:=3: unknown parameter"),
        (["--params-file", f"{d}/unknown.yaml"], "unknown parameter 'num_robotz'"),
        (["--params-file", f"{d}/bad_value.yaml"],
         f"params file {d}/bad_value.yaml: /**: decision_timeout must be > 0, got -1.0"),
        (["--cell-size", "0.5"], "--cell-size applies to a Nav2 map"),
        (["--map", f"{d}/b.yaml", "--resolution", "0.5"], "--resolution does not apply"),
        (["--instance", f"{d}/i.yaml", "--num-robots", "3"], "--num-robots does not apply"),
        (["--arrival-timeout", "3"], "--arrival-timeout applies to --real-robots"),
        (["--goal-seed", "3"], "--goal-seed applies to --task-source lifelong"),
        (["--density", "1.5"], "--density must be in [0, 1), got 1.5"),
        (["--ros-args", "-p", "tick_period:=-1.0"], "tick_period must be >= 0, got -1.0"),
        (["--ros-args", "-p", "status_period:=0.0"], "status_period must be > 0"),
        (["--max-steps", "0"], "--max-steps must be >= 1 with task_source instance"),
        (["--ros-args", "-p", "ranking:=best"], "ranking must be one of"),
    ]


def test_every_bad_value_is_refused_before_anything_starts(tmp_path, checkpoints):
    for argv, expected in _bad(tmp_path):
        with pytest.raises(launcher.UpError) as caught:
            _prepare(argv, checkpoints["dhc"])
        text = str(caught.value)
        assert "\n" not in text and expected in text, (argv, text)


@pytest.mark.ros
def test_up_refuses_in_one_line_with_exit_2(tmp_path, ros_env, checkpoints):
    (tmp_path / "afile").write_text("x")
    done = subprocess.run(CLI + ["up", "--checkpoint", checkpoints["dhc"], "--record",
                                 str(tmp_path / "afile" / "r.json"), "--quiet"], env=ros_env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().count("\n") == 0 and "Traceback" not in done.stderr
    assert "--record" in done.stderr


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
                    "    max_steps: 2\n    decision_timeout: 3\n")
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


def test_a_nav2_map_reading_unknown_grey_as_free_is_warned_about(tmp_path, checkpoints):
    """map_saver writes unknown as grey 205; under Nav2's default free_thresh 0.25 it reads as
    free (map_server does the same), which `up --help` would have a user believe blocks."""
    from mapf_fleet.grid.nav2_map import write_nav2_map

    pixels = np.zeros((6, 8), dtype=np.int64)
    pixels[0, :3] = -1  # unknown
    path = tmp_path / "building.yaml"
    write_nav2_map(path, pixels, 0.5)
    _, plan, _ = _prepare(["--map", str(path), "--num-robots", "2"], checkpoints["dhc"])
    assert not any("grey 205" in w for w in plan.warnings)  # 0.196: unknown blocks
    path.write_text(path.read_text().replace("free_thresh: 0.196", "free_thresh: 0.25"))
    _, plan, _ = _prepare(["--map", str(path), "--num-robots", "2"], checkpoints["dhc"])
    assert any("3 pixels of grey 205" in w and "free_thresh 0.25" in w for w in plan.warnings)
