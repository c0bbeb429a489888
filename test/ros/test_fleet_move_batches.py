"""One message per policy process per tick (issue 40, Scale): a fleet of 6 robots in 2 policy
processes sends its moves as one RobotMoves per process and tick on /fleet/move_batches (none
on the per-robot /fleet/moves) and the simulator plays every tick with no decision missed; with
the policy parameter `per_robot_messages` the same fleet sends one RobotMove per robot and tick
on /fleet/moves instead (the per-robot topic the docs promise, still served). The numbers of
the moves are checked by the fleet == evaluator tests (test_fleet_equivalence.py), which run
the batched path.

The bags hold every tick from tick 0 because `up --bag`'s recorder subscribes to the fleet
state (which tick 0 waits for) only once it has matched every policy process's moves publisher
(bag.py, `--expect`; test_tick0_listeners.py). Before that the first ticks' bag could hold 2,
1 or 0 batches (a race: this test was xfail); it is run repeatedly to show the race is gone."""

# Loopback only: every ROS process these tests start runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
# and its own ROS_DOMAIN_ID (test/conftest.py, ros_env / _isolate_ros_tests).

from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter

import pytest

UP = [sys.executable, "-m", "mapf_fleet.cli", "up"]


def _run_with_bag(tmp_path, name, env, checkpoint, extra=()):
    from rosbags.rosbag2 import Reader

    from mapf_fleet.ros.bag import fleet_typestore

    bag, record = tmp_path / f"{name}_bag", tmp_path / f"{name}.json"
    proc = subprocess.run(
        UP + ["--checkpoint", checkpoint, "--num-robots", "6", "--size", "10", "--seed", "4",
              "--max-steps", "10", "--task-source", "lifelong", "--nodes-per-process", "3",
              "--record", str(record), "--bag", str(bag), "--quiet", *extra],
        env=env, capture_output=True, text=True, timeout=240)
    text = proc.stdout + proc.stderr
    assert proc.returncode == 0 and record.exists(), text
    run = json.loads(record.read_text())
    typestore = fleet_typestore()
    topics = {}
    with Reader(bag) as reader:
        for connection, _, raw in reader.messages():
            if connection.topic in ("/fleet/moves", "/fleet/move_batches"):
                msg = typestore.deserialize_cdr(raw, connection.msgtype)
                if msg.episode == run["episode"]:
                    topics.setdefault(connection.topic, []).append(msg)
    return run, topics, text


@pytest.mark.ros
@pytest.mark.slow
def test_a_policy_process_sends_one_move_message_per_tick(tmp_path, ros_env, checkpoints):
    run, topics, text = _run_with_bag(tmp_path, "batched", ros_env, checkpoints["dcc"])
    assert run["steps"] == 10 and run["missed_decisions"] == 0, text
    batches = topics.get("/fleet/move_batches", [])
    assert "/fleet/moves" not in topics, text
    # ticks 0..9: one batch of each process (3 robots each) per tick, every robot once
    assert Counter(b.tick for b in batches) == {t: 2 for t in range(10)}, text
    for tick in range(10):
        robots = sorted(int(r) for b in batches if b.tick == tick for r in b.robot_ids)
        assert robots == list(range(6)), tick
    assert all(len(b.robot_ids) == 3 and len(b.preferences) == 15 for b in batches)
    # the moves played are the batches' first choices
    played = {(b.tick, int(r)): int(b.preferences[5 * k]) for b in batches
              for k, r in enumerate(b.robot_ids)}
    assert [[played[(t, i)] for i in range(6)] for t in range(10)] == run["actions"]


@pytest.mark.ros
@pytest.mark.slow
def test_per_robot_messages_sends_a_robot_move_per_robot(tmp_path, ros_env, checkpoints):
    run, topics, text = _run_with_bag(tmp_path, "per_robot", ros_env, checkpoints["dcc"],
                                      ["--ros-args", "-p", "per_robot_messages:=true"])
    assert run["steps"] == 10 and run["missed_decisions"] == 0, text
    moves = topics.get("/fleet/moves", [])
    assert "/fleet/move_batches" not in topics, text
    assert Counter(m.tick for m in moves) == {t: 6 for t in range(10)}, text
    played = {(m.tick, int(m.robot_id)): int(m.action) for m in moves}
    assert [[played[(t, i)] for i in range(6)] for t in range(10)] == run["actions"]
