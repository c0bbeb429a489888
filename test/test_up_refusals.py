"""`mapf-fleet up` refuses, in one line and before anything starts, what it used to ignore or
crash on (issue 40, item 8 and "Scale"): `--planning-budget` without `--conflict-rule lacam`,
`--single-process` with `--nodes-per-process`, a `--size` whose map does not fit in memory
(was a MemoryError traceback); and without `--nodes-per-process` it chooses the layout and says
so (512 robots were started as 512 processes)."""

# Loopback only: every ROS process these tests start runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
# and its own ROS_DOMAIN_ID (test/conftest.py, ros_env / _isolate_ros_tests).

from __future__ import annotations

import subprocess
import sys

import pytest

from mapf_fleet.ros import launcher
from mapf_fleet.ros.launcher import UpError


def test_planning_budget_without_lacam_is_refused():
    with pytest.raises(UpError, match=r"^--planning-budget applies to --conflict-rule lacam "
                                      r"only \(the conflict rule is pibt_anchor_swap_lns\)"):
        launcher.prepare(["--planning-budget", "0.5"])
    args, plan, _ = launcher.prepare(["--planning-budget", "0.5", "--conflict-rule", "lacam"])
    assert plan.sim["planning_budget"] == 0.5


def test_single_process_with_nodes_per_process_is_refused():
    with pytest.raises(UpError, match=r"^--nodes-per-process applies to policy processes; "
                                      r"--single-process"):
        launcher.prepare(["--single-process", "--nodes-per-process", "2"])
    args, _, _ = launcher.prepare(["--single-process"])
    assert args.single_process


def test_without_nodes_per_process_up_chooses_the_layout_and_says_so():
    args, _, n = launcher.prepare(["--num-robots", "512", "--size", "80"])
    assert n == 512 and args.nodes_per_process >= 64  # 8 processes, fewer if memory is short
    assert args.layout_note.startswith("512 robots in ") and "\n" not in args.layout_note
    args, _, _ = launcher.prepare(["--num-robots", "8"])
    assert args.nodes_per_process == 1 and not getattr(args, "layout_note", "")
    args, _, _ = launcher.prepare(["--num-robots", "8", "--nodes-per-process", "3"])
    assert args.nodes_per_process == 3  # given: kept


def test_a_huge_size_is_one_line_and_exit_2_not_a_memory_error():
    done = subprocess.run([sys.executable, "-m", "mapf_fleet.cli", "up", "--size", "100000"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "mapf-fleet up: --size 100000: generating a 100000x100000 map takes about"), done.stderr
    assert done.stdout == ""
