"""Bad input at the entry points is one line on stderr (file, field, value) and exit code 2, never
a traceback: `mapf-fleet` sub-commands, `mapf-fleet node ...`, the node
processes `up` starts (`python -m mapf_fleet.ros.run`) and the stand-in robots."""

from __future__ import annotations

import subprocess
import sys

import pytest

CLI = [sys.executable, "-m", "mapf_fleet.cli"]
RUN = [sys.executable, "-m", "mapf_fleet.ros.run"]
STAND_IN = [sys.executable, "-m", "mapf_fleet.ros.stand_in_robot"]


@pytest.fixture(scope="module")
def bad_files(tmp_path_factory, checkpoints):
    import torch

    folder = tmp_path_factory.mktemp("bad_input")
    good = open(checkpoints["dhc"], "rb").read()
    (folder / "truncated.pt").write_bytes(good[:1000])
    (folder / "corrupt.pt").write_bytes(b"not a checkpoint at all\n" * 10)
    torch.save({"weights": torch.zeros(3)}, folder / "foreign.pt")  # torch file, not ours
    (folder / "bad.map").write_text("type octile\nheight 2\nwidth 3\nmap\n...\n.@\n")
    (folder / "bad.scen").write_text("version 1\n")
    (folder / "no_goals.yaml").write_text('grid: ["...."]\nstarts: [[0, 0]]\n')
    # continuous operation's inputs: a building map without its resolution, a bad task
    (folder / "building.yaml").write_text("image: map.pgm\norigin: [0, 0, 0]\nnegate: 0\n"
                                          "occupied_thresh: 0.65\nfree_thresh: 0.196\n")
    (folder / "tasks.yaml").write_text("tasks:\n  - goal: [1, 1]\n  - {goal: [2]}\n")
    return folder


# (id, command, text the one line must contain)
CASES = [
    ("policy-no-checkpoint", CLI + ["node", "policy"], "parameter 'checkpoint' is required"),
    ("evaluate-truncated", CLI + ["evaluate", "--checkpoint", "{d}/truncated.pt", "--sizes", "40",
                                  "--agents", "4", "--instances", "1"],
     "truncated.pt: not a readable checkpoint"),
    ("render-corrupt", CLI + ["render", "--checkpoint", "{d}/corrupt.pt", "--size", "10",
                              "--agents", "2", "--out", "{d}/x.gif"],
     "corrupt.pt: not a readable checkpoint"),
    ("render-foreign", CLI + ["render", "--checkpoint", "{d}/foreign.pt", "--size", "10",
                              "--agents", "2", "--out", "{d}/x.gif"], "foreign.pt: field format"),
    ("simulator-bad-map-row", CLI + ["node", "simulator", "--ros-args", "-p",
                                     "map_file:={d}/bad.map", "-p", "scen_file:={d}/bad.scen"],
     "bad.map:6: row has 2 characters, expected 3"),
    ("simulator-bad-map-row-run", RUN + ["simulator", "--ros-args", "-p", "map_file:={d}/bad.map",
                                         "-p", "scen_file:={d}/bad.scen"],
     "bad.map:6: row has 2 characters"),
    ("aggregator-instance-missing-field", CLI + ["node", "aggregator", "--ros-args", "-p",
                                                 "instance_file:={d}/no_goals.yaml"],
     "no_goals.yaml: missing field 'goals'"),
    ("stand-in-instance-missing-field", STAND_IN + ["--instance", "{d}/no_goals.yaml"],
     "no_goals.yaml: missing field 'goals'"),
    ("stand-in-bad-map", STAND_IN + ["--map", "{d}/bad.map", "--num-robots", "2"],
     "bad.map:6: row has 2 characters"),
    ("up-decision-timeout-0", CLI + ["up", "--decision-timeout", "0", "--single-process",
                                     "--num-robots", "2", "--size", "8", "--checkpoint",
                                     "{dhc}", "--quiet"], "--decision-timeout must be > 0"),
    # every value refused before anything starts (these once ran, or failed late)
    ("up-max-steps-0", CLI + ["up", "--max-steps", "0", "--checkpoint", "{dhc}", "--quiet"],
     "--max-steps must be >= 1"),
    ("up-max-steps-negative", CLI + ["up", "--max-steps", "-5", "--checkpoint", "{dhc}",
                                     "--quiet"], "--max-steps must be >= 1"),
    ("up-tick-period-negative", CLI + ["up", "--checkpoint", "{dhc}", "--quiet", "--ros-args",
                                       "-p", "tick_period:=-1.0"],
     "-p tick_period:=-1.0: tick_period must be >= 0, got -1.0"),
    ("up-comm-timeout-0", CLI + ["up", "--comm-timeout", "0", "--checkpoint", "{dhc}",
                                 "--quiet"], "--comm-timeout must be > 0"),
    ("up-startup-timeout-0", CLI + ["up", "--startup-timeout", "0", "--checkpoint", "{dhc}",
                                    "--quiet"], "--startup-timeout must be > 0"),
    ("up-status-period-0", CLI + ["up", "--checkpoint", "{dhc}", "--quiet", "--ros-args", "-p",
                                  "status_period:=0.0"], "status_period must be > 0"),
    ("simulator-num-robots-abc", CLI + ["node", "simulator", "--ros-args", "-p",
                                        "num_robots:=abc"], "'num_robots' to 'abc'"),
    ("node-missing-params-file", CLI + ["node", "simulator", "--params-file",
                                        "{d}/missing.yaml"], "missing.yaml"),
    ("up-missing-params-file", CLI + ["up", "--params-file", "{d}/missing.yaml", "--checkpoint",
                                      "{dhc}", "--quiet"], "missing.yaml"),
    ("echo-bogus-type", CLI + ["echo", "/fleet/map", "--type", "bogus", "--timeout", "1"],
     "bogus"),
    # continuous operation
    ("up-map-yaml-missing-field", CLI + ["up", "--map", "{d}/building.yaml", "--checkpoint",
                                         "{dhc}", "--quiet"], "building.yaml: field 'resolution'"),
    ("up-task-file-bad-task", CLI + ["up", "--task-source", "tasks", "{d}/tasks.yaml",
                                     "--checkpoint", "{dhc}", "--quiet"],
     "tasks.yaml:3: task 1: field 'goal'"),
    ("up-task-source-unknown", CLI + ["up", "--task-source", "forever", "--checkpoint", "{dhc}",
                                      "--quiet"], "--task-source must be one of"),
    ("up-task-source-tasks-no-file", CLI + ["up", "--task-source", "tasks", "--checkpoint",
                                            "{dhc}", "--quiet"], "needs exactly one task file"),
    ("goal-bad-robot", CLI + ["goal", "three", "--cell", "1", "1"], "ROBOT must be a robot id"),
    ("simulator-task-file-missing", CLI + ["node", "simulator", "--ros-args", "-p",
                                           "task_source:=tasks", "-p",
                                           "task_file:={d}/missing_tasks.yaml"],
     "missing_tasks.yaml: cannot read the task file"),
]


@pytest.mark.ros
@pytest.mark.parametrize("command,expected", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_and_exit_2(command, expected, bad_files, checkpoints, ros_env):
    command = [arg.format(d=bad_files, dhc=checkpoints["dhc"]) for arg in command]
    env = dict(ros_env)  # test/conftest.py: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, own domain
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    env.pop("MAPF_FLEET_TRACEBACK", None)
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=180)
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert "Traceback" not in done.stderr, done.stderr
    assert done.returncode == 2, (done.returncode, done.stderr)
    assert len(lines) == 1, done.stderr
    assert expected in lines[0], lines[0]
