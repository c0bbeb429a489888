"""A real `mapf-fleet up` and its children under bursts of SIGINT and SIGTERM, and `up` killed
with SIGKILL: every process of the fleet is gone within the bound docs/fleet.md states
("Stopping and errors"), whatever the moment (start-up, mid-run, the end of the run).

The fleet's processes are found by the MAPF_FLEET_PARENT_PID that `up` puts in each child's
environment (/proc/<pid>/environ keeps it), so an orphan re-parented to init is found too."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from mapf_fleet.stop_signals import PARENT_PID_ENV

UP = [sys.executable, "-m", "mapf_fleet.cli", "up"]
# docs/fleet.md, "Stopping and errors": every process gone within this after a stop signal
STOP_BOUND_S = 20.0
# and after a kill -9 of `up`: its children stop on their own (PR_SET_PDEATHSIG, or when their
# entry point installs its handlers); a child still importing on a loaded machine takes longer
ORPHAN_BOUND_S = 60.0


def _stat(pid: int) -> list[str] | None:
    """/proc/<pid>/stat's fields after the command name (state first), None when gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None


class _Fleet:
    """The processes `up` started: its children (parent `up`), and any process whose
    environment names `up` as its parent (MAPF_FLEET_PARENT_PID: found after `up` is gone too),
    each kept with its start time (a pid used again is another process)."""

    def __init__(self, up: subprocess.Popen):
        self.up = up
        self.seen: dict[int, str] = {}

    def look(self) -> None:
        marker = f"{PARENT_PID_ENV}={self.up.pid}".encode()
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit() or int(entry.name) == self.up.pid:
                continue
            stat = _stat(int(entry.name))
            if stat is None or stat[0] == "Z":
                continue
            mine = int(stat[1]) == self.up.pid
            if not mine:
                try:
                    mine = marker in (entry / "environ").read_bytes().split(b"\0")
                except OSError:
                    continue
            if mine:
                self.seen.setdefault(int(entry.name), stat[19])  # field 22: start time

    def alive(self) -> list[int]:
        self.look()
        left = []
        for pid, started in self.seen.items():
            stat = _stat(pid)
            if stat is not None and stat[0] != "Z" and stat[19] == started:
                left.append(pid)
        return left

    def gone_within(self, seconds: float) -> tuple[bool, list[int]]:
        """Wait until `up` has exited and every process of its fleet is gone."""
        deadline = time.monotonic() + seconds
        left = []
        while time.monotonic() < deadline:
            left = self.alive()
            if self.up.poll() is not None and not left:
                return True, []
            time.sleep(0.2)
        return False, left + ([self.up.pid] if self.up.poll() is None else [])

    def kill_all(self) -> None:
        for pid in self.alive() + ([self.up.pid] if self.up.poll() is None else []):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.up.wait()


class _Output:
    """`up`'s output read by a thread: the lines, and when a line with `text` came."""

    def __init__(self, proc: subprocess.Popen):
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc):
        for line in proc.stdout:
            self.lines.append(line)

    def wait_for(self, text: str, timeout: float, fleet: "_Fleet") -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(text in line for line in self.lines):
                return True
            fleet.look()
            time.sleep(0.05)
        return False

    def text(self) -> str:
        self._thread.join(5)
        return "".join(self.lines)


def _start_up(ros_env, checkpoints, tmp_path, max_steps: int) -> tuple[subprocess.Popen, _Output]:
    env = dict(ros_env)
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    proc = subprocess.Popen(
        UP + ["--checkpoint", checkpoints["dhc"], "--num-robots", "4", "--size", "10",
              "--nodes-per-process", "2", "--max-steps", str(max_steps),
              "--task-source", "lifelong",  # runs to max_steps: the end is known
              "--record", str(tmp_path / "run.json"),
              "--ros-args", "-p", "tick_period:=0.2", "-p", "progress_every:=1"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True)  # its own process group: a burst to the group, as `timeout` does
    return proc, _Output(proc)


def _burst(proc: subprocess.Popen, rng: random.Random) -> int:
    """Ctrl-C held down, or `timeout`'s signal to the command and its group: 2-200 SIGINT /
    SIGTERM in a row, to `up` and to its process group."""
    sent = 0
    for _ in range(rng.randint(2, 200)):
        signum = rng.choice((signal.SIGINT, signal.SIGTERM))
        try:
            if rng.random() < 0.5:
                os.kill(proc.pid, signum)
            else:
                os.killpg(proc.pid, signum)
        except ProcessLookupError:
            break
        sent += 1
        if rng.random() < 0.1:
            time.sleep(rng.uniform(0.0, 0.05))
    return sent


def _sleep_looking(fleet: _Fleet, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        fleet.look()
        time.sleep(0.05)


MOMENTS = ("start-up", "mid-run", "end")


@pytest.mark.ros
@pytest.mark.slow
def test_bursts_of_stop_signals_at_random_moments_end_every_process_of_the_fleet(
        tmp_path, ros_env, checkpoints):
    rng = random.Random(40)
    rounds = int(os.environ.get("MAPF_FLEET_STOP_ROUNDS", "12"))
    for round_ in range(rounds):
        moment = MOMENTS[round_ % len(MOMENTS)]
        max_steps = 15
        (tmp_path / f"r{round_}").mkdir()
        proc, out = _start_up(ros_env, checkpoints, tmp_path / f"r{round_}", max_steps)
        fleet = _Fleet(proc)
        try:
            if moment == "start-up":  # the processes importing, DDS discovery, tick 0 not yet
                _sleep_looking(fleet, rng.uniform(0.2, 6.0))
            elif moment == "mid-run":
                assert out.wait_for("tick 3", 180, fleet), out.text()
                _sleep_looking(fleet, rng.uniform(0.0, 1.0))
            elif round_ % 2:  # as the run ends (the case: "success" just printed)
                assert out.wait_for(f"tick {max_steps - 2}:", 180, fleet), out.text()
                _sleep_looking(fleet, rng.uniform(0.0, 0.8))
            else:  # the run over: `up` stopping its children, reporting
                assert out.wait_for("outcome:", 180, fleet), out.text()
            fleet.look()
            sent = _burst(proc, rng)
            gone, left = fleet.gone_within(STOP_BOUND_S)
            if not gone:
                fleet.kill_all()
            assert gone, (f"round {round_} ({moment}, {sent} signals): still running after "
                          f"{STOP_BOUND_S:.0f} s: {left}\n{out.text()[-3000:]}")
            codes = {0, 1, 130, 143}  # the run's outcome, or 128 + the first signal
            # Python's default handlers before `up` installs its own (the interpreter starting,
            # `mapf_fleet.cli` importing) and after its finalization resets them: a signal then
            # ends `up` by the signal (SIGINT: a KeyboardInterrupt), with no child running
            by_signal = {-signal.SIGINT, -signal.SIGTERM}
            if moment != "mid-run":
                codes |= by_signal
            assert proc.returncode in codes, (round_, moment, proc.returncode,
                                              out.text()[-3000:])
            if proc.returncode not in by_signal:
                assert "Traceback" not in out.text(), out.text()
        finally:
            fleet.kill_all()


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("moment", ["start-up", "mid-run"])
def test_kill_9_of_up_leaves_no_orphan(tmp_path, ros_env, checkpoints, moment):
    """`up` killed with SIGKILL: its children get SIGTERM (PR_SET_PDEATHSIG), and one still
    importing then (SIGTERM ignored until its handlers exist) sees its parent gone when it
    installs them: none is left running."""
    proc, out = _start_up(ros_env, checkpoints, tmp_path, max_steps=400)
    fleet = _Fleet(proc)
    try:
        if moment == "start-up":  # the children still importing: SIGTERM ignored until then
            deadline = time.monotonic() + 60
            while len(fleet.alive()) < 3 and time.monotonic() < deadline:
                time.sleep(0.02)
        else:
            assert out.wait_for("tick 3", 180, fleet), out.text()
        assert len(fleet.alive()) == 3, fleet.seen  # 2 policy processes and the simulator
        proc.kill()
        proc.wait()
        deadline = time.monotonic() + ORPHAN_BOUND_S
        while time.monotonic() < deadline and fleet.alive():
            time.sleep(0.2)
        left = fleet.alive()
        assert not left, f"orphans {ORPHAN_BOUND_S:.0f} s after kill -9 of up: {left}"
    finally:
        fleet.kill_all()
