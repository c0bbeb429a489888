"""Two fleets on one ROS_DOMAIN_ID: topic and service names are relative, so
fleets in different namespaces (`up --namespace`, `-r __ns:=`) do not hear each other; and a
policy hub serves one run at a time (fleet.lockstep.EpisodeBinding), so a second simulator never takes
over robots that serve another simulator's run."""

from __future__ import annotations

import json
import subprocess
import sys
from types import SimpleNamespace

import pytest

from mapf_fleet.fleet.lockstep import EpisodeBinding, FleetTicker

CLI = [sys.executable, "-m", "mapf_fleet.cli"]


def test_a_hub_serves_one_episode_until_it_ends_or_its_simulator_is_gone():
    binding = EpisodeBinding(timeout=30.0)
    assert binding.reported == 0                       # free
    assert binding.accept(111, False, now=0.0)         # the first state binds it
    assert binding.reported == 111
    assert not binding.accept(222, False, now=10.0)    # a foreign simulator mid-run: ignored
    assert binding.accept(111, False, now=20.0)
    assert not binding.accept(222, False, now=49.0)    # 29 s after episode 111's last state
    assert binding.accept(222, False, now=50.1)        # 111 silent for 30 s: gone, 222 binds
    assert binding.reported == 222
    assert binding.accept(222, True, now=51.0)         # 222 ends (done): free again
    assert binding.reported == 0
    assert binding.accept(333, False, now=51.5)


def test_a_simulator_counts_only_free_robots_or_its_own_as_ready():
    ticker = FleetTicker(2, episode=555)

    def status(robot, episode):
        return SimpleNamespace(robot_id=robot, episode=episode, ready=True, peers=2)

    ticker.on_status(status(0, 999))   # serving another simulator's run
    ticker.on_status(status(1, 0))     # free
    assert ticker.unready() == [0]
    ticker.on_status(status(0, 555))   # serving ours
    assert ticker.unready() == []


@pytest.mark.ros
@pytest.mark.slow
def test_two_fleets_in_two_namespaces_on_one_domain_both_succeed(tmp_path, ros_env):
    """Two `up` fleets (4 robots each, the shipped checkpoint) at once on the same domain, in
    /fleet_a and /fleet_b: each run succeeds with its own robots (no missed decision, each
    robot's move came from its own fleet), and its topics live under its namespace."""
    # ros_env (test/conftest.py): ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, one domain for both
    assert ros_env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    fleets = {}
    for name, seed in (("fleet_a", 0), ("fleet_b", 1)):
        record = tmp_path / f"{name}.json"
        proc = subprocess.Popen(
            CLI + ["up", "--namespace", f"/{name}", "--num-robots", "4", "--size", "12",
                   "--seed", str(seed), "--nodes-per-process", "4", "--record", str(record),
                   "--max-steps", "64"],
            env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        fleets[name] = (proc, record)
    outputs = {}
    try:
        for name, (proc, _) in fleets.items():
            outputs[name] = proc.communicate(timeout=400)[0]
    finally:
        for proc, _ in fleets.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    episodes = set()
    for name, (proc, record) in fleets.items():
        out = outputs[name]
        assert proc.returncode == 0, out
        run = json.loads(record.read_text())
        assert run["success"] and run["missed_decisions"] == 0, run["summary"]
        assert len(run["positions"][0]) == 4
        assert "all 4 robots ready" in out, out
        episodes.add(run["episode"])
    assert len(episodes) == 2
