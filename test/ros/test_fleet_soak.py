"""Soak test: a continuous 64-robot fleet (lifelong goals: a new goal on arrival) in
the large-fleet layout (4 processes x 16 robots, DCC with communicating weights, so requests and
replies cross processes every tick) runs 320 ticks without a missed decision, and its tick time at the end is not far above its tick time
at the start. It once grew over the run (a service client created per
robot pair as robots met new peers) until every decision was missed. The ratio is generous
(3x, medians of 50 ticks) and there is no absolute time: the machine may be busy."""

from __future__ import annotations

import json
import re
import statistics
import subprocess
import sys

import pytest

TICKS = 320
TICK_LINE = re.compile(r"\[(\d+\.\d+)\] \[[^\]]*mapf_simulator\]: tick (\d+): ")


def tick_seconds(output: str) -> list[float]:
    """Seconds per tick between the simulator's progress lines (every 10 ticks: each also
    checkpoints the run's record, which would dominate if it were every tick)."""
    stamps = [(int(m[2]), float(m[1])) for m in TICK_LINE.finditer(output)]
    return [(b[1] - a[1]) / (b[0] - a[0]) for a, b in zip(stamps, stamps[1:]) if b[0] > a[0]]


@pytest.mark.ros
@pytest.mark.slow
def test_64_robots_320_ticks_flat_and_no_missed_decision(tmp_path, ros_env, checkpoints):
    env = dict(ros_env)  # test/conftest.py: own ROS_DOMAIN_ID, LOCALHOST discovery
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    record = tmp_path / "run.json"
    done = subprocess.run(
        [sys.executable, "-m", "mapf_fleet.cli", "up", "--checkpoint",
         checkpoints["dcc_sensitive"], "--num-robots", "64", "--size", "32", "--seed", "4",
         "--nodes-per-process", "16", "--task-source", "lifelong", "--max-steps", str(TICKS),
         "--record", str(record),
         "--log-dir", str(tmp_path / "logs"), "--ros-args", "-p", "progress_every:=10"],
        env=env, capture_output=True, text=True, timeout=1500)
    assert record.exists(), done.stdout[-3000:] + done.stderr[-3000:]
    run = json.loads(record.read_text())
    assert run["steps"] == TICKS, run["summary"]  # lifelong: the run goes on to the limit
    assert run["missed_decisions"] == 0, run["summary"]
    # the robots really talked across processes, through the batched DCC service
    assert sum(len(r) for tick in run["requested"] for r in tick) > 0
    logs = "".join(p.read_text() for p in (tmp_path / "logs").glob("*.log"))
    assert re.search(r"to other processes [1-9]\d* in [1-9]\d* batch calls", logs), logs[-2000:]
    ticks = tick_seconds(done.stdout)  # one per 10 ticks
    assert len(ticks) >= TICKS // 10 - 2, done.stdout[-2000:]
    start = statistics.median(ticks[:5])  # ticks 10-60
    end = statistics.median(ticks[-5:])  # the last 50
    assert end <= 3 * start, (f"tick time grew over the run: median {1000 * start:.0f} ms at "
                              f"ticks 10-60, {1000 * end:.0f} ms over the last 50")
