"""Faults and supervision, the plain-Python pieces (no ROS graph): the pose check (NaN, inf,
jumps), stop signals, a lockstep run stopped at tick k, the supervision of `mapf-fleet up`'s
children (a dead policy process reported with its last lines, a signal passed on once, nothing
left running), `up`'s checkpoint and layout checks, its ticks/s, and the policy hub's notice
that the fleet state stopped coming."""

from __future__ import annotations

import json
import os
import signal
import sys
import textwrap
import time

import numpy as np
import pytest

from mapf_fleet.fleet.arbiter import check_pose
from mapf_fleet.ros.common import MapGeometry
from mapf_fleet.fleet.run import FleetRun
from mapf_fleet.fleet.tasks import InstanceTasks
from mapf_fleet.fleet.lockstep import FleetTicker

GRID = np.zeros((4, 4), dtype=np.uint8)
GRID[1, 1] = 1


# ---- the pose check ----
@pytest.mark.parametrize("x, y, field, value", [
    (float("nan"), 0.5, "pose.position.x", "nan"),
    (0.5, float("inf"), "pose.position.y", "inf"),
    (float("-inf"), 0.5, "pose.position.x", "-inf"),
])
def test_check_pose_rejects_non_finite_coordinates_naming_field_and_value(x, y, field, value):
    checked = check_pose(GRID, MapGeometry(), x, y, last=(0, 0))
    assert checked.cell is None and checked.raw is None
    assert field in checked.reason and value in checked.reason


def test_check_pose_rejects_a_jump_of_two_cells_and_accepts_one_move():
    geometry = MapGeometry()
    # robot 0 from (0, 0) to (2, 0): x is the column, y the row
    jump = check_pose(GRID, geometry, *geometry.cell_to_xy(2, 0), last=(0, 0))
    assert jump.cell is None and jump.raw == (2, 0)
    assert "jump of 2 cells" in jump.reason and "0,0" in jump.reason and "2,0" in jump.reason
    diagonal = check_pose(GRID, geometry, *geometry.cell_to_xy(1, 2), last=(0, 1))
    assert diagonal.cell is None and "jump of 2 cells" in diagonal.reason
    assert check_pose(GRID, geometry, *geometry.cell_to_xy(1, 0), last=(0, 0)).cell == (1, 0)
    assert check_pose(GRID, geometry, *geometry.cell_to_xy(0, 0), last=(0, 0)).cell == (0, 0)
    # the first pose (no last cell) may be anywhere free; off-grid and obstacles as before
    assert check_pose(GRID, geometry, *geometry.cell_to_xy(3, 3)).cell == (3, 3)
    assert "off the 4x4 grid" in check_pose(GRID, geometry, -5.0, 0.5).reason
    assert "on an obstacle" in check_pose(GRID, geometry, 1.5, 1.5, last=(1, 0)).reason


# ---- a stopped lockstep run ----
def test_stopped_ticker_returns_at_once_and_the_outcome_says_stopped_at_tick(tmp_path):
    ticker = FleetTicker(2, episode=5, tick=7)
    ticker.stop()
    started = time.monotonic()
    assert ticker.wait_ready(30.0) == [0, 1]
    decisions = ticker.collect(30.0)
    assert time.monotonic() - started < 20.0  # not the 60 s of the two timeouts, on any load
    assert decisions.missing == [0, 1]
    run = FleetRun(np.zeros((3, 3)), [[0, 0], [2, 2]], InstanceTasks(), [[1, 1], [2, 2]],
                   max_steps=50, episode=5)
    outcome = run.finish(stopped_at=7)
    assert outcome["success"] is False
    assert outcome["summary"].startswith("stopped at tick 7: 1/2 robots on goal")
    run.recorder.write(tmp_path / "run.json")
    assert json.loads((tmp_path / "run.json").read_text())["stopped_at_tick"] == 7


def test_stop_signals_turn_sigint_and_sigterm_into_a_request_without_traceback():
    from mapf_fleet.ros.processes import StopSignals

    with StopSignals() as signals:
        assert not signals.requested and signals.exit_code is None
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)  # the handler runs in the main thread, between bytecodes
        assert signals.requested and signals.exit_code == 143 and not signals.forced
        os.kill(os.getpid(), signal.SIGINT)  # a second signal: no KeyboardInterrupt either
        time.sleep(0.05)
        assert signals.forced and signals.exit_code == 143 and signals.name == "SIGTERM"
    assert signal.getsignal(signal.SIGINT) is not signals._handle


# ---- supervision of up's children ----
def _script(tmp_path, name, body):
    path = tmp_path / name
    path.write_text(textwrap.dedent(body))
    return [sys.executable, str(path)]


MAIN = """
    import signal, sys, time
    def stop(signum, frame):
        print(f"stopping on {signum}", flush=True)
        sys.exit(128 + signum)
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    print("running", flush=True)
    while True:
        time.sleep(0.05)
"""


def _wait_for(predicate, timeout=20.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return False


def test_every_child_runs_on_loopback_whatever_its_env_says(tmp_path):
    """Child forces ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, even over a caller's SUBNET."""
    from mapf_fleet.ros.common import prepare_environment
    from mapf_fleet.ros.processes import Child

    assert prepare_environment({"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"})[
        "ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    for env in ({**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"},
                {k: v for k, v in os.environ.items() if k != "ROS_AUTOMATIC_DISCOVERY_RANGE"}):
        child = Child("probe", [sys.executable, "-c", "import os; "
                                "print(os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE'))"], env)
        assert child.proc.wait(30) == 0
        assert child.tail() == ["LOCALHOST"]


def test_a_dead_policy_process_is_reported_with_its_last_lines_and_stops_the_run(tmp_path):
    from mapf_fleet.ros.processes import Child, StopSignals, supervise

    lines = []
    main = Child("simulator", _script(tmp_path, "main.py", MAIN), dict(os.environ),
                 echo=lines.append)
    dying = Child("policy process (robots 0-3)", _script(tmp_path, "dying.py", """
        import sys, time
        time.sleep(0.5)
        print("loading the model", flush=True)
        sys.exit("bad.pt: not a readable checkpoint (truncated)")
    """), dict(os.environ), log_path=str(tmp_path / "policy.log"))
    healthy = Child("policy process (robots 4-7)", _script(tmp_path, "healthy.py", MAIN),
                    dict(os.environ), log_path=str(tmp_path / "healthy.log"))
    warnings = []
    started = time.monotonic()
    code, problem = supervise(main, [dying, healthy], StopSignals(), warn=warnings.append)
    assert time.monotonic() - started < 300  # the healthy ones run forever: it did not wait
    assert problem == "policy process (robots 0-3) exited with code 1"
    text = "\n".join(warnings)
    assert "policy process (robots 0-3) exited with code 1; its last output lines:" in text
    assert "bad.pt: not a readable checkpoint (truncated)" in text
    assert "loading the model" in text
    assert code == 128 + signal.SIGINT and "stopping on 2" in lines  # asked to stop, once
    assert all(c.poll() is not None for c in (main, dying, healthy))  # nothing left running


def test_a_stop_signal_is_passed_on_once_and_every_child_is_stopped(tmp_path):
    from mapf_fleet.ros.processes import Child, StopSignals, supervise

    lines = []
    main = Child("simulator", _script(tmp_path, "main.py", MAIN), dict(os.environ),
                 echo=lines.append)
    policy = Child("policy process (robots 0-7)", _script(tmp_path, "policy.py", MAIN),
                   dict(os.environ), log_path=str(tmp_path / "policy.log"))
    assert _wait_for(lambda: "running" in lines)
    signals = StopSignals()
    signals._handle(signal.SIGTERM, None)  # as if `up` got SIGTERM
    code, problem = supervise(main, [policy], signals, warn=lambda text: None)
    assert (code, problem) == (143, "")
    assert lines.count("stopping on 15") == 1
    assert policy.poll() is not None


STUBBORN = {
    # caught, then nothing: stuck after the signal reached it
    "stuck": "signal.signal(signal.SIGINT, lambda *a: None)",
    # ignored for good (child_setup's state): stuck while starting up
    "starting": "signal.signal(signal.SIGINT, signal.SIG_IGN)",
}


@pytest.mark.parametrize("state", sorted(STUBBORN))
def test_a_simulator_that_does_not_stop_is_killed_after_its_grace(tmp_path, state):
    from mapf_fleet.ros.processes import Child, StopSignals, signal_disposition, supervise

    lines = []
    main = Child("simulator", _script(tmp_path, "stubborn.py", f"""
        import signal, time
        {STUBBORN[state]}
        print("running", flush=True)
        while True:
            time.sleep(0.05)
    """), dict(os.environ), echo=lines.append)
    assert _wait_for(lambda: "running" in lines, timeout=60.0)
    assert signal_disposition(main.proc.pid, signal.SIGINT) == (
        "caught" if state == "stuck" else "ignored")
    signals = StopSignals()
    signals._handle(signal.SIGINT, None)
    warnings = []
    started = time.monotonic()
    # the grace that applies is 1 s, the other one would fail the test
    graces = {"grace": 1.0, "startup_grace": 600.0} if state == "stuck" else \
        {"grace": 600.0, "startup_grace": 1.0}
    code, _ = supervise(main, [], signals, warn=warnings.append, **graces)
    assert time.monotonic() - started < 300  # the 1 s grace applied, not the 600 s one
    assert code == -signal.SIGKILL and "did not stop in time: killed" in warnings[0]


def test_a_stop_waits_for_a_simulator_still_starting_up_and_reaches_it_once(tmp_path):
    """A child of `up` ignores SIGINT / SIGTERM until its entry point installs its handlers (a
    signal sent before is lost); on a loaded machine that can take longer than the grace. The
    stop is sent once the child catches it, and the grace counts from then."""
    from mapf_fleet.ros.processes import Child, StopSignals, supervise

    lines = []
    slow_start = """
    import time
    print("importing", flush=True)
    time.sleep(3.0)  # a slow start: SIGINT / SIGTERM still ignored (child_setup)
"""
    main = Child("simulator", _script(tmp_path, "late.py", slow_start + MAIN), dict(os.environ),
                 echo=lines.append)
    assert _wait_for(lambda: "importing" in lines, timeout=60.0)
    signals = StopSignals()
    signals._handle(signal.SIGINT, None)  # as if `up` got Ctrl-C while the child starts
    warnings = []
    code, problem = supervise(main, [], signals, grace=1.0, warn=warnings.append)
    assert (code, problem) == (130, ""), warnings
    assert lines.count("stopping on 2") == 1 and not warnings


def test_stop_request_sends_once_the_child_catches_it_and_counts_the_grace_from_then(
        monkeypatch):
    """StopRequest's clock (no processes): a child still ignoring the signal gets nothing and
    `startup_grace`; once it catches it, one signal and `grace`. Where the dispositions cannot
    be read, the signal goes at once, again from 5 s on, and `grace` counts from the first."""
    from types import SimpleNamespace

    from mapf_fleet.ros import processes

    sent = []
    child = SimpleNamespace(proc=SimpleNamespace(pid=12345), poll=lambda: None,
                            send_signal=sent.append)
    state = {"now": "ignored"}
    monkeypatch.setattr(processes, "signal_disposition", lambda pid, signum: state["now"])
    stop = processes.StopRequest(child, grace=10.0, startup_grace=100.0)
    stop.request(signal.SIGINT, now=0.0)
    stop.step(50.0)
    assert sent == [] and not stop.overdue(99.0) and stop.overdue(100.5)
    state["now"] = "caught"
    stop.step(60.0)
    stop.step(65.5)  # no resend to a child known to have it
    assert sent == [signal.SIGINT] and not stop.overdue(69.9) and stop.overdue(70.1)
    stop.step(68.1)  # still there 2 s before its grace ends: a second signal, once
    stop.step(69.5)
    assert sent == [signal.SIGINT] * 2
    stop.force(61.0)
    assert stop.overdue(62.1)
    stop.request(signal.SIGTERM, now=62.0)  # another signal after the first: sent as well
    assert sent == [signal.SIGINT] * 2 + [signal.SIGTERM]

    sent.clear()
    state["now"] = None  # not Linux: no dispositions
    stop = processes.StopRequest(child, grace=10.0, startup_grace=100.0)
    stop.request(signal.SIGTERM, now=0.0)
    assert sent == [signal.SIGTERM]
    stop.step(4.0)
    stop.step(5.1)
    assert sent == [signal.SIGTERM] * 2
    assert not stop.overdue(9.9) and stop.overdue(10.1)


# ---- up's checks and report ----
def test_up_checks_the_checkpoint_before_anything_starts(tmp_path):
    from mapf_fleet.ros.launcher import checked_checkpoint, default_checkpoint

    good = default_checkpoint()
    problem, metadata = checked_checkpoint(good)
    assert good and problem == "" and metadata.get("algorithm") in ("dcc", "dhc")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(open(good, "rb").read(1000))  # head -c 1000 models/default.pt > bad.pt
    problem, metadata = checked_checkpoint(str(bad))
    assert "not a readable checkpoint" in problem and str(bad) in problem and metadata == {}
    assert "\n" not in problem


def test_up_refuses_too_many_nodes_in_one_process_with_the_reason():
    from mapf_fleet.ros.launcher import MAX_NODES_PER_PROCESS, layout_problem

    problem = layout_problem(10000, True, 1)
    assert "--single-process" in problem and str(MAX_NODES_PER_PROCESS) in problem
    assert "square" in problem and "--nodes-per-process" in problem
    assert "--nodes-per-process 2000" in layout_problem(10000, False, 2000)
    assert layout_problem(10000, False, 8) == ""
    assert layout_problem(MAX_NODES_PER_PROCESS, True, 1) == ""


def test_up_warns_above_the_measured_discovery_limit_of_processes():
    from mapf_fleet.ros.launcher import MAX_DISCOVERED_PROCESSES, layout_warning

    assert MAX_DISCOVERED_PROCESSES == 32
    assert layout_warning(31, False, 1) == ""  # 31 policy processes + the simulator
    warning = layout_warning(32, False, 1)
    assert "33 ROS processes" in warning and "--nodes-per-process 2" in warning
    assert "34 ROS processes" in layout_warning(32, False, 1, recorder=True)
    assert "--nodes-per-process 5" in layout_warning(128, False, 4)  # 32 hubs + simulator
    assert layout_warning(128, False, 5) == "" and layout_warning(10000, True, 1) == ""


def test_up_reports_ticks_per_second_from_the_first_tick(tmp_path, capsys):
    from mapf_fleet.ros.launcher import report

    record = tmp_path / "run.json"
    record.write_text(json.dumps({"steps": 10, "run_seconds": 2.0, "success": True,
                                  "summary": "success: 4/4 robots on goal after 10 steps"}))
    assert report(str(record), 12.0) == 0  # 10 s of start-up before the first tick
    out = capsys.readouterr().out
    assert "5.00 ticks/s" in out and "wall time 12.0 s" in out


# ---- the hub notices that the fleet state stopped coming ----
def test_state_watch_logs_once_when_the_state_stops_coming():
    from mapf_fleet.ros.hub import StateWatch

    watch = StateWatch(timeout=5.0, now=0.0)
    assert watch.silence(now=4.0) is None
    first = watch.silence(now=6.0)
    assert first and "no fleet state yet" in first
    assert watch.silence(now=60.0) is None                   # once per silence
    assert watch.note(3, False, now=61.0) == "fleet state received again (tick 3)"
    assert watch.silence(now=65.0) is None
    text = watch.silence(now=67.0)                           # the simulator was killed
    assert text and "since tick 3" in text and "stopped or is unreachable" in text
    watch.note(9, True, now=70.0)                            # the run ended: quiet is normal
    assert watch.silence(now=200.0) is None


def test_a_stop_before_the_run_started_ends_every_child_within_seconds(tmp_path):
    """Ctrl-C while a big fleet starts up: nothing ran yet, so the policy processes (here
    stuck, ignoring the signal, as while importing) are killed at once, and a simulator still
    starting up gets 3 s, not the 120 s a running one gets to catch the signal."""
    from mapf_fleet.ros.processes import Child, StopSignals, supervise

    lines = []
    main = Child("simulator", _script(tmp_path, "slow.py", STUBBORN["starting"].join(
        ["import signal, time\n", "\nprint('importing', flush=True)\ntime.sleep(600)\n"])),
        dict(os.environ), echo=lines.append)
    policies = [Child(f"policy process {i}", _script(tmp_path, f"p{i}.py",
                                                       "import signal, time\n"
                                                       "signal.signal(signal.SIGTERM, "
                                                       "signal.SIG_IGN)\ntime.sleep(600)\n"),
                      dict(os.environ), log_path=str(tmp_path / f"p{i}.log")) for i in range(4)]
    assert _wait_for(lambda: "importing" in lines, timeout=60.0)
    signals = StopSignals()
    signals._handle(signal.SIGINT, None)
    started = time.monotonic()
    code, problem = supervise(main, policies, signals, warn=lambda text: None,
                              running=lambda: False)
    assert time.monotonic() - started < 15, time.monotonic() - started
    assert all(c.poll() is not None for c in [main] + policies)


def test_a_run_that_never_starts_is_reported_and_stopped(tmp_path):
    """Every start-up wait is bounded: a simulator stuck before its first tick (a stale Fast
    DDS shared-memory file froze fleets so, whatever --startup-timeout said) is reported."""
    from mapf_fleet.ros.processes import Child, StopSignals, supervise

    main = Child("simulator", _script(tmp_path, "stuck.py", "import time\ntime.sleep(600)\n"),
                 dict(os.environ))
    warnings = []
    started = time.monotonic()
    code, problem = supervise(main, [], StopSignals(), warn=warnings.append,
                              running=lambda: False, start_deadline=1.0)
    assert time.monotonic() - started < 15
    assert problem == "the simulator's run did not start within 1 s", warnings
    assert "stuck while starting up" in warnings[0] and main.poll() is not None


def test_empty_fast_dds_port_files_are_found_and_fresh_ones_left(tmp_path):
    from mapf_fleet.ros.processes import STALE_AFTER_S, stale_shm_files

    now = time.time()
    for name, size, age in [("fastrtps_port7008", 0, 60), ("fastrtps_port7010", 0, 1),
                            ("fastrtps_port7012", 64, 60), ("fastrtps_port7008_el", 0, 60),
                            ("fastrtps_port7014_sl", 0, 60),
                            ("fastrtps_1234abcd", 0, 60)]:
        path = tmp_path / name
        path.write_bytes(b"x" * size)
        os.utime(path, (now - age, now - age))
    assert STALE_AFTER_S < 60
    assert stale_shm_files(now, str(tmp_path)) == [str(tmp_path / "fastrtps_port7008")]
