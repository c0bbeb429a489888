"""`mapf-fleet up` as a new user meets it: every option has help and its default stated,
--resolution / --origin for real robots, a .scen's own robot count, --log-dir and the logs of a
failed run kept, `mapf-fleet param`, --single-process with 128 robots ready without waiting out
the start-up timeout, and the policy nodes' default ranking following the checkpoint's recorded
ranking, else the conflict rule. The bad values refused up front are in test_cli_errors.py."""

from __future__ import annotations

import argparse
import glob
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mapf_fleet.ros import launcher

CLI = [sys.executable, "-m", "mapf_fleet.cli"]
RUN = [sys.executable, "-m", "mapf_fleet.ros.run"]


def _plan(argv: list[str], checkpoint: str):
    """`up`'s options and its nodes' parameters as its main() prepares them, before it starts
    anything."""
    args, plan, _ = launcher.prepare(["--checkpoint", checkpoint] + list(argv))
    return args, plan


def test_every_up_option_has_help_and_states_its_default():
    parser = launcher.build_parser()
    formatter = parser._get_formatter()
    for action in parser._actions:
        if not action.option_strings or isinstance(action, argparse._HelpAction):
            continue
        assert action.help, f"{action.option_strings[0]} has no help text"
        text = formatter._get_help_string(action)
        number = isinstance(action.default, (int, float)) and not isinstance(action.default,
                                                                              bool)
        if number or action.type in (int, float):
            assert "default" in text, f"{action.option_strings[0]}: no default in {text!r}"
    shown = " ".join(parser.format_help().split())
    for stated in ("default: 256", "(default: 10.0)", "(default: 5.0)", "(default: 120.0)",
                   "(default: 0.3)", "seed of a generated instance (default: 0)",
                   "default: chosen from the robot count and the memory available",
                   "default: 8 generated"):
        assert stated in shown, stated


def test_resolution_and_origin_reach_the_aggregator(checkpoints):
    args, plan = _plan(["--real-robots", "--resolution", "0.05", "--origin", "1.5", "-2",
                        "--num-robots", "2"], checkpoints["dhc"])
    sim = plan.values["mapf_aggregator"]
    assert (sim["resolution"], sim["origin_x"], sim["origin_y"]) == (0.05, 1.5, -2.0)
    # the simulator takes --resolution; it has no origin (its map's corner is 0, 0)
    _, plan = _plan(["--resolution", "0.5"], checkpoints["dhc"])
    assert plan.sim["resolution"] == 0.5 and "origin_x" not in plan.sim
    with pytest.raises(launcher.UpError, match="--origin applies to --real-robots"):
        _plan(["--origin", "1", "2"], checkpoints["dhc"])
    with pytest.raises(launcher.UpError, match="--resolution must be > 0"):
        _plan(["--resolution", "0"], checkpoints["dhc"])


def test_map_and_scen_without_num_robots_take_the_files_count(tmp_path, checkpoints):
    (tmp_path / "room.map").write_text("type octile\nheight 3\nwidth 4\nmap\n....\n.@..\n....\n")
    lines = ["version 1"] + [f"0\troom.map\t4\t3\t{c}\t0\t{c}\t2\t2" for c in (0, 1, 2, 3)]
    (tmp_path / "room.scen").write_text("\n".join(lines) + "\n")
    files = ["--map", str(tmp_path / "room.map"), "--scen", str(tmp_path / "room.scen")]
    args, plan = _plan(files, checkpoints["dhc"])
    assert plan.sim["num_robots"] == 4 and len(plan.values) == 1 + 4  # the file's count
    args, plan = _plan(files + ["--num-robots", "2"], checkpoints["dhc"])
    assert plan.sim["num_robots"] == 2 and len(plan.values) == 1 + 2  # given: kept
    args, plan = _plan([], checkpoints["dhc"])
    assert plan.sim["num_robots"] == 8  # a generated instance


def _policy_nodes(plan, checkpoint, tmp_path, robots=(0,)):
    """Policy nodes started from the merged params file `up` writes for `plan`."""
    import rclpy

    from mapf_fleet.fleet import parameters as P
    from mapf_fleet.ros.policy_node import make_policy_nodes

    plan = plan.with_run_files(params_path=str(tmp_path / "merged.yaml"))
    P.write_params_file(plan.params_path, plan.values, plan.namespace)
    context = rclpy.Context()
    rclpy.init(args=["policy"] + plan.ros_args(), context=context)
    try:
        nodes = make_policy_nodes(list(robots), context=context)
        found = [n.ranking for n in nodes]
        for node in nodes:
            node.destroy_node()
        return found
    finally:
        rclpy.try_shutdown(context=context)


@pytest.mark.ros
def test_default_ranking_follows_the_rule_and_yields_to_a_params_file(
        tmp_path, checkpoints, ros_env):
    """No ranking given: the rule's default (`default_ranking`: today confidence under
    pibt_anchor, q under pibt and revert). A params file's (or the command line's) ranking wins
    whatever the rule, the deprecated preference_mode too: `up` passes the policy nodes its
    conflict rule, never a ranking of its own."""
    from mapf_fleet.coordination.ranking import default_ranking

    params = tmp_path / "p.yaml"
    params.write_text("/**:\n  ros__parameters:\n    ranking: q_demote_stay\n")
    old = tmp_path / "old.yaml"
    old.write_text("/**:\n  ros__parameters:\n    preference_mode: q_demote_stay\n")
    assert default_ranking("pibt_anchor") != default_ranking("pibt")  # the rule matters
    cases = [([], default_ranking("pibt_anchor")), (["--conflict-rule", "pibt"], "q"),
             (["--conflict-rule", "revert"], "q"),
             (["--params-file", str(params)], "q_demote_stay"),  # no rule's default
             (["--params-file", str(old)], "q_demote_stay"),  # the deprecated name
             (["--params-file", str(params), "--conflict-rule", "pibt"], "q_demote_stay"),
             (["--ranking", "distance", "--params-file", str(params)], "distance")]
    for own, expected in cases:
        _, plan = _plan(own + ["--num-robots", "2"], checkpoints["dhc"])
        assert _policy_nodes(plan, checkpoints["dhc"], tmp_path) == [expected], own


@pytest.mark.ros
def test_a_node_reads_the_deprecated_preference_mode_with_a_warning(tmp_path, checkpoints,
                                                                   ros_env):
    """Old params files given to a node directly (`mapf-fleet node policy --params-file`)."""
    import rclpy

    from mapf_fleet.ros.policy_node import PolicyNode

    old = tmp_path / "old.yaml"
    old.write_text("/**:\n  ros__parameters:\n    preference_mode: distance\n")
    context = rclpy.Context()
    rclpy.init(args=["policy", "--ros-args", "--params-file", str(old)], context=context)
    try:
        node = PolicyNode(robot_id=0, checkpoint=checkpoints["dhc"], context=context)
        assert node.ranking == "distance"
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


@pytest.mark.ros
def test_default_ranking_is_the_checkpoints_recorded_ranking(tmp_path, ros_env):
    """A checkpoint recording its ranking for the rule (metadata rankings, e.g. a DAgger round):
    the policy nodes use it when no ranking is given, the rule's default under another
    rule, and a given ranking (params file, --ranking) still wins. The robots a
    process hosts beside the first (sharing its model) rank the same."""
    import torch

    from mapf_fleet.coordination.ranking import default_ranking
    from mapf_fleet.models.checkpoint import build_model, save_checkpoint
    from mapf_fleet.models.config import ModelConfig

    torch.manual_seed(7)
    from mapf_fleet.coordination.rules import FLEET_RULE

    recorded = "q_then_distance"
    assert recorded != default_ranking(FLEET_RULE)  # the checkpoint's, not the rule's
    checkpoint = str(save_checkpoint(tmp_path / "round.pt",
                                     build_model(ModelConfig.preset("dhc", "small")), {
        "alpha": 0.0, "curriculum": {}, "learner_steps": 0, "training_config": {},
        "rankings": {FLEET_RULE: recorded}}))
    params = tmp_path / "p.yaml"
    params.write_text("/**:\n  ros__parameters:\n    ranking: q_demote_stay\n")
    cases = [([], recorded), (["--conflict-rule", "pibt"], default_ranking("pibt")),
             (["--params-file", str(params)], "q_demote_stay"),
             (["--ranking", "confidence"], "confidence")]
    for own, expected in cases:
        _, plan = _plan(own + ["--num-robots", "2"], checkpoint)
        assert _policy_nodes(plan, checkpoint, tmp_path, (0, 1)) == [expected, expected], own


def _up(ros_env, *argv, timeout=240):
    env = dict(ros_env)  # test/conftest.py: own ROS_DOMAIN_ID, LOCALHOST discovery
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    return subprocess.run(CLI + ["up", *argv], env=env, capture_output=True, text=True,
                          timeout=timeout)


@pytest.mark.ros
@pytest.mark.slow
def test_log_dir_keeps_the_policy_logs_and_a_failed_run_keeps_them_too(tmp_path, ros_env,
                                                                      checkpoints):
    small = ["--checkpoint", checkpoints["dhc"], "--num-robots", "2", "--size", "8",
             "--max-steps", "1", "--quiet"]
    logs = tmp_path / "logs"
    done = _up(ros_env, *small, "--log-dir", str(logs))
    kept = sorted(Path(p).name for p in glob.glob(str(logs / "*.log")))
    assert kept == ["policy_0-0.log", "policy_1-1.log"], (kept, done.stdout, done.stderr)
    assert "hub timing" in (logs / "policy_0-0.log").read_text()  # what the hub said
    # no --log-dir: one tick of random weights fails (robots not on goal), the logs stay
    done = _up(ros_env, *small)
    assert done.returncode == 1, done.stdout + done.stderr
    line = [x for x in done.stderr.splitlines() if "logs are kept in" in x]
    assert line, done.stderr
    folder = line[0].split("logs are kept in ")[1].strip()
    try:
        assert sorted(Path(p).name for p in glob.glob(os.path.join(folder, "*.log"))) == kept
    finally:
        import shutil

        shutil.rmtree(folder, ignore_errors=True)


@pytest.mark.ros
@pytest.mark.slow
def test_single_process_128_robots_are_ready_without_the_startup_timeout(ros_env, checkpoints):
    """The one executor once spun every robot's node: the heartbeats of 128 robots
    were not taken in time and `up` waited out the whole start-up timeout."""
    done = _up(ros_env, "--single-process", "--checkpoint", checkpoints["dcc"],
               "--num-robots", "128", "--size", "40", "--max-steps", "1",
               "--startup-timeout", "90", timeout=400)
    assert "all 128 robots ready" in done.stdout + done.stderr, done.stdout[-3000:] + done.stderr
    assert "starting without ready robots" not in done.stdout + done.stderr


@pytest.mark.ros
def test_param_get_set_list_on_a_running_simulator(ros_env):
    env = dict(ros_env)
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    sim = subprocess.Popen(RUN + ["simulator", "--ros-args", "-p", "num_robots:=2", "-p",
                                  "size:=8", "-p", "startup_timeout:=120.0"], env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    def param(*argv):
        return subprocess.run(CLI + ["param", *argv, "--timeout", "30"], env=env,
                              capture_output=True, text=True, timeout=120)

    try:
        listed = param("list", "mapf_simulator")
        assert listed.returncode == 0, listed.stderr
        assert "tick_period: 0.0" in listed.stdout and "num_robots: 2" in listed.stdout
        assert param("get", "mapf_simulator", "tick_period").stdout.strip() == "0.0"
        done = param("set", "mapf_simulator", "tick_period", "1")  # an int, sent as a double
        assert done.returncode == 0 and "set tick_period = 1.0" in done.stdout, done.stderr
        assert param("get", "/mapf_simulator", "tick_period").stdout.strip() == "1.0"
        refused = param("set", "mapf_simulator", "max_steps", "5")
        assert refused.returncode == 1
        assert "read at start-up, cannot change during a run" in refused.stderr
        refused = param("set", "mapf_simulator", "tick_period", "-1")
        assert refused.returncode == 1 and "must be >= 0" in refused.stderr
        missing = param("get", "mapf_simulator", "no_such_parameter")
        assert missing.returncode == 1 and "no parameter 'no_such_parameter'" in missing.stderr
    finally:
        sim.terminate()
        try:
            sim.wait(20)
        except subprocess.TimeoutExpired:
            sim.kill()
            sim.wait()
    gone = subprocess.run(CLI + ["param", "get", "mapf_simulator", "tick_period", "--timeout",
                                 "1"], env=env, capture_output=True, text=True, timeout=60)
    assert gone.returncode == 1 and "no parameter services of node /mapf_simulator" in \
        gone.stderr
