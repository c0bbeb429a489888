"""Process plumbing of the fleet (plain Python, no rclpy): stop signals, child processes and
their supervision by `mapf-fleet up`.

- `StopSignals` (from `mapf_fleet.stop_signals`): SIGINT and SIGTERM become a stop request (a
  flag, waits woken through a self-pipe) that the process acts on,
  as `ros2 launch` users expect: the run ends cleanly (record and "stopped at tick k" outcome
  written, children stopped), no KeyboardInterrupt traceback (not on a second Ctrl-C either), and
  the exit code is 128 + the signal (130 / 143). The fleet's processes call
  `rclpy.init(signal_handler_options=SignalHandlerOptions.NO)`, so rclpy's handlers do not shut
  the context down under a running tick ("Failed to publish: publisher's context is invalid").
- `Child`: a child process whose output goes to a log file (or is echoed line by line), with its
  last lines for a report.
- `supervise`: `mapf-fleet up`'s loop over its children.
"""

from __future__ import annotations

import collections
import os
import re
import signal
import subprocess
import sys
import threading
import time

# the stop signals live below every layer (the trainer uses them too); re-exported here
from mapf_fleet.stop_signals import (PARENT_PID_ENV, STOP_SIGNALS, StopSignals,  # noqa: F401
                                     signal_name, stop_signals)

# Environment every process of the fleet runs with: nothing leaves loopback,
# and the venv is the ROS prefix so ament lookups work. (Here, below `common`, which re-exports
# it: the two modules used to import each other.)
FLEET_ENV = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}


def prepare_environment(env: dict | None = None) -> dict:
    """Return (and apply to os.environ when env is None) the variables every fleet process needs.
    The discovery range is always LOCALHOST, whatever the caller's environment says: no process
    of the project sends DDS traffic off this machine."""
    target = os.environ if env is None else env
    target.update(FLEET_ENV)
    if "AMENT_PREFIX_PATH" not in target:
        target["AMENT_PREFIX_PATH"] = sys.prefix
    return target


def _prctl():
    try:
        import ctypes

        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):  # not Linux
        return None


_PRCTL = _prctl()
PR_SET_PDEATHSIG = 1


def child_setup() -> None:
    """`preexec_fn` of a child of `up`:
    - it gets SIGTERM when its parent dies (Linux), so not even a `kill -9` of `mapf-fleet up`
      leaves orphans (the prctl function is looked up beforehand: nothing is imported between
      fork and exec);
    - SIGINT and SIGTERM start ignored, until its entry point installs `stop_signals()`: a stop
      that comes while it is still importing is not a KeyboardInterrupt traceback (nor a
      death without a record); `supervise` sends it again until it is gone."""
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, int(signal.SIGTERM))
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)


def exit_text(code: int | None) -> str:
    if code is None:
        return "is running"
    if code < 0:
        return f"was killed by {signal_name(-code)}"
    return f"exited with code {code}"


class Child:
    """A child process named `name` (for reports). Its stdout and stderr go to `log_path`, or
    else are read line by line by a thread that passes each line to `echo` (None: discard) and
    keeps the last ones. It runs in its own session, so a terminal's Ctrl-C reaches the parent
    only (which passes it on once), and gets SIGTERM when the parent dies (`child_setup`)."""

    def __init__(self, name: str, argv: list[str], env: dict, log_path: str | None = None,
                 echo=None, keep_lines: int = 40):
        self.name = name
        # every child stays on loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST), whoever built env
        env = prepare_environment(dict(env))
        # the child stops if this process is gone before it catches SIGTERM (`stop_signals`)
        env[PARENT_PID_ENV] = str(os.getpid())
        self._lines: collections.deque[str] = collections.deque(maxlen=keep_lines)
        self.log_path = log_path
        self._reader = None
        if log_path is not None:
            with open(log_path, "wb") as log:
                self.proc = subprocess.Popen(argv, env=env, stdin=subprocess.DEVNULL,
                                             stdout=log, stderr=subprocess.STDOUT,
                                             start_new_session=True,
                                             preexec_fn=child_setup)
        else:
            self.proc = subprocess.Popen(argv, env=env, stdin=subprocess.DEVNULL,
                                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                         text=True, errors="replace", start_new_session=True,
                                         preexec_fn=child_setup)
            self._reader = threading.Thread(target=self._read, args=(echo,),
                                            name=f"output of {name}", daemon=True)
            self._reader.start()

    def _read(self, echo) -> None:
        for line in self.proc.stdout:
            line = line.rstrip("\n")
            self._lines.append(line)
            if echo is not None:
                echo(line)

    def poll(self) -> int | None:
        return self.proc.poll()

    def send_signal(self, signum: int) -> None:
        if self.proc.poll() is None:
            try:
                self.proc.send_signal(signum)
            except ProcessLookupError:
                pass

    def wait_output(self, timeout: float = 2.0) -> None:
        """Wait until the echo thread has read everything (after the process ended)."""
        if self._reader is not None:
            self._reader.join(timeout)

    def tail(self, lines: int = 15) -> list[str]:
        """The last `lines` lines of its output."""
        if self.log_path is None:
            self.wait_output()
            return list(self._lines)[-lines:]
        try:
            with open(self.log_path, "rb") as log:
                log.seek(0, os.SEEK_END)
                log.seek(max(0, log.tell() - 16384))
                text = log.read().decode("utf-8", "replace")
        except OSError:
            return []
        return text.splitlines()[-lines:]

    def report(self, lines: int = 15) -> str:
        """'<name> <exit text>; its last output lines:' and the lines, indented."""
        tail = [line for line in self.tail(lines) if line.strip()]
        text = f"{self.name} {exit_text(self.poll())}"
        if not tail:
            return text + " (no output)"
        return text + "; its last output lines:\n" + "\n".join(f"    {line}" for line in tail)


def stop_children(children: list[Child], grace: float = 3.0) -> None:
    """SIGTERM, then SIGKILL what did not stop within `grace` s (a hung Fast DDS process may
    ignore SIGTERM)."""
    for child in children:
        child.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace
    for child in children:
        try:
            child.proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            child.proc.kill()
            child.proc.wait()
    for child in children:
        child.wait_output(1.0)


def signal_disposition(pid: int, signum: int) -> str | None:
    """What process `pid` does with `signum`: "caught" (a handler), "ignored" or "default",
    read from /proc/<pid>/status (Linux); None when that cannot be read."""
    try:
        with open(f"/proc/{pid}/status") as status:
            masks = dict(line.split(":", 1) for line in status if line.startswith("Sig"))
        bit = 1 << (int(signum) - 1)
        if int(masks["SigCgt"], 16) & bit:
            return "caught"
        return "ignored" if int(masks["SigIgn"], 16) & bit else "default"
    except (OSError, KeyError, ValueError):
        return None


class StopRequest:
    """Asks a child to stop with a signal and says when it is overdue (then it is killed).

    A child of `up` ignores SIGINT and SIGTERM until its entry point installs its handlers
    (`child_setup`): a signal sent before is lost, and on a loaded machine the imports before
    that can take many seconds. So, where the child's dispositions can be read
    (`signal_disposition`), the signal is sent once the child catches it (or would die of it)
    and the child has `grace` s from then; it has `startup_grace` s from the request to get
    there (stuck while starting up: killed). Where they cannot be read, the signal is sent at
    once, again every 2 s from 5 s on, and `grace` counts from the first. A child that caught
    it but is still there 2 s before its grace ends gets it again (its second signal: it stops
    waiting for a clean end, and exits without being killed). A request with another signal
    after the first was sent is sent too; `force()` leaves the child 1 s."""

    def __init__(self, child: "Child", grace: float, startup_grace: float):
        self.child = child
        self.grace = float(grace)
        self.startup_grace = float(startup_grace)
        self.signum: int | None = None
        self.sent: set[int] = set()
        self._deadline = float("inf")
        self._forced_deadline = float("inf")
        self._resend = float("inf")
        self._unknown = False

    def request(self, signum: int, now: float) -> None:
        if self.signum is None:
            self._deadline = now + self.startup_grace
        self.signum = int(signum)
        self.step(now)

    def force(self, now: float) -> None:
        if self.signum is not None:
            self._forced_deadline = min(self._forced_deadline, now + 1.0)

    def step(self, now: float) -> None:
        """Send what is due: the requested signal once the child catches it; again where its
        dispositions are unknown, or to a child still there near the end of its grace."""
        if self.signum is None:
            return
        if self.signum in self.sent:
            if now > self._resend:  # lost (dispositions unknown), or stuck: again
                self.child.send_signal(self.signum)
                self._resend = now + 2.0 if self._unknown else float("inf")
            return
        state = signal_disposition(self.child.proc.pid, self.signum)
        if state == "ignored" and self.child.poll() is None:
            return  # still starting up: the signal would be lost
        if not self.sent:
            self._deadline = now + self.grace
        self.child.send_signal(self.signum)
        self.sent.add(self.signum)
        self._unknown = state is None
        self._resend = (now + 5.0 if self._unknown
                        else max(now + 0.5 * self.grace, self._deadline - 2.0))

    def overdue(self, now: float) -> bool:
        return now > min(self._deadline, self._forced_deadline)


def supervise(main: Child, others: list[Child], signals: StopSignals, *, grace: float = 10.0,
              startup_grace: float = 120.0, poll: float = 0.1, echoed: bool = False,
              watched: list[Child] = (), running=lambda: True,
              start_deadline: float = float("inf"),
              warn=lambda text: print(text, file=sys.stderr, flush=True)) -> tuple[int, str]:
    """Wait for `main` (the simulator or aggregator: it ends the run) while watching `others`.

    - A stop signal is passed on to `main` (`StopRequest`: once `main` catches it, i.e. has
      installed its handlers, up to `startup_grace` s after the request), which ends its run
      (record, outcome) and exits with 128 + the signal; if it has not exited `grace` s after
      receiving it (it gets the signal again 2 s before; 1 s after a second signal to `up`),
      it is killed.
    - Another child ending while the run goes on is reported with its last output lines (`warn`)
      and `main` is asked to stop (SIGINT) the same way.
    - `main` ending otherwise than with 0, 1 or the signal it was sent is reported (with its last
      lines unless they were `echoed` already).
    - Before `running()` (main's run has started: its first tick), nothing is lost by stopping
      at once: a stop signal ends the others within seconds (SIGTERM, then SIGKILL) and leaves
      main 3 s to catch it and 5 s to end ("stopped at tick 0"); a run not started
      `start_deadline` s after this call is reported (stuck while starting up: e.g. a stale
      Fast DDS shared-memory file) and every child stopped.
    Every child is stopped before this returns, except the `watched` ones (watched like
    `others`, stopped by the caller: e.g. a recorder, after the fleet). (main's exit code, the
    problem reported or "").
    """
    problem = ""
    sent: set[int] = set()  # signals asked of main: it may exit with 128 + one of them
    stop = StopRequest(main, grace, startup_grace)
    killed = False
    begun = time.monotonic()
    started = False
    try:
        while main.poll() is None:
            now = time.monotonic()
            started = started or running()
            if not started and not signals.requested and now - begun > start_deadline:
                problem = f"the {main.name}'s run did not start within {start_deadline:.0f} s"
                warn(f"mapf-fleet up: {problem} (a process stuck while starting up; "
                     f"{shm_hint()})")
                stop_children([main] + list(others), grace=2.0)
                return main.proc.wait(), problem
            if not started and signals.requested and not sent:
                # nothing to keep but main's "stopped at tick 0": the others go now, main
                # gets a few seconds to say so (a main still importing is killed)
                stop.grace, stop.startup_grace = 5.0, 3.0
                stop_children(list(others), grace=2.0)
            if signals.requested and signals.signum not in sent:
                sent.add(signals.signum)
                stop.request(signals.signum, now)
            if not problem and not signals.requested:
                dead = [c for c in list(others) + list(watched) if c.poll() is not None]
                if dead:
                    problem = "; ".join(f"{c.name} {exit_text(c.poll())}" for c in dead)
                    for child in dead:
                        warn(f"mapf-fleet up: {child.report()}")
                    warn(f"mapf-fleet up: stopping the {main.name}")
                    sent.add(int(signal.SIGINT))
                    stop.request(signal.SIGINT, now)
            stop.step(now)
            if signals.forced:
                stop.force(now)
            if stop.overdue(now) and main.poll() is None:
                warn(f"mapf-fleet up: the {main.name} did not stop in time: killed" if started
                     else f"mapf-fleet up: the {main.name} was still starting up: stopped")
                main.proc.kill()
                killed = True
                break
            if signals.requested:  # a second signal is seen within `poll`
                time.sleep(poll)
            else:
                signals.wait(poll)  # wakes at once on a signal (self-pipe); takes no lock
        code = main.proc.wait()
    finally:
        stop_children([main] + list(others))
    expected = {0, 1} | {128 + s for s in sent} | {-s for s in sent}
    if killed:
        expected.add(-int(signal.SIGKILL))
    if code not in expected and not problem:
        if code < 0 or code >= 128:  # killed, or died of a signal: no outcome of its own
            problem = f"{main.name} {exit_text(code)}"
            warn(f"mapf-fleet up: {problem}" if echoed else f"mapf-fleet up: {main.report()}")
        elif not echoed:  # its own error (e.g. 2: a bad parameter): show its message
            warn(f"mapf-fleet up: {main.report()}")
    return code, problem


SHM_DIR = "/dev/shm"
PORT_FILE = re.compile(r"fastrtps_port\d+")
STALE_AFTER_S = 10.0  # a zero-byte port file older than this is no port being created


def stale_shm_files(now: float | None = None, folder: str = SHM_DIR) -> list[str]:
    """Fast DDS shared-memory port files (`fastrtps_port<N>`) left empty by a process killed
    while creating them: every later participant opening that port waits forever (a fleet of
    nine or more processes froze at start-up in any domain)."""
    now = time.time() if now is None else now
    found = []
    try:
        names = os.listdir(folder)
    except OSError:
        return found
    for name in names:
        if not PORT_FILE.fullmatch(name):  # a port itself; its _el / _sl locks are empty
            continue
        path = os.path.join(folder, name)
        try:
            info = os.stat(path)
        except OSError:
            continue
        if info.st_size == 0 and now - info.st_mtime > STALE_AFTER_S:
            found.append(path)
    return sorted(found)


def remove_stale_shm(warn=lambda text: print(text, file=sys.stderr, flush=True)) -> list[str]:
    """Remove the stale port files (`stale_shm_files`), saying which; those that cannot be
    removed (another user's) are named with the command that removes them."""
    removed, kept = [], []
    for path in stale_shm_files():
        try:
            os.remove(path)
            removed.append(path)
        except OSError:
            kept.append(path)
    if removed:
        warn(f"mapf-fleet up: removed {len(removed)} empty Fast DDS shared-memory port "
             f"file(s) left by a killed run ({', '.join(removed)}): they freeze every fleet "
             f"that opens them")
    if kept:
        warn(f"mapf-fleet up: warning: empty Fast DDS shared-memory port file(s) "
             f"{', '.join(kept)} may freeze the fleet at start-up; remove them (sudo rm "
             f"{' '.join(kept)})")
    return removed


def shm_hint() -> str:
    stale = stale_shm_files()
    if stale:
        return f"empty Fast DDS port files in {SHM_DIR}: {', '.join(stale)}"
    return f"Fast DDS shared memory in {SHM_DIR}/fastrtps_*: `fastdds shm clean` removes unused files"


def clean_zombie_shm(warn=lambda text: print(text, file=sys.stderr, flush=True),
                     timeout: float = 20.0) -> int:
    """`fastdds shm clean`: remove the Fast DDS shared-memory segments and ports no live
    process holds (their locks are free), e.g. those of children killed while stopping a run;
    says how many. Returns that count (0 when the tool is missing or fails)."""
    import shutil

    tool = shutil.which("fastdds")
    if tool is None:
        return 0
    try:
        done = subprocess.run([tool, "shm", "clean"], capture_output=True, text=True,
                              timeout=timeout)
    except (OSError, subprocess.TimeoutExpired):
        return 0
    found = re.findall(r"(\d+) zombie (ports|segments) cleaned", done.stdout)
    count = sum(int(n) for n, _ in found)
    if count:
        warn(f"mapf-fleet up: removed {count} unused Fast DDS shared-memory files "
             f"({', '.join(f'{n} {kind}' for n, kind in found)}) left by stopped processes")
    return count
