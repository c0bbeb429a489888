"""Stop signals of every long-running command (`mapf-fleet up` and its processes, `train`,
`dagger`, `echo`, `record`): SIGINT and SIGTERM become a stop request that the process acts on
at its own pace, as `ros2 launch` users expect. Standard library only, below every layer, so
`ros` and `training` share it.

A signal must always end the process, even a burst of them (Ctrl-C held down, GNU `timeout`
signalling the command and its process group at once). So the handler only assigns attributes:
no lock, no logging, no `threading.Event.set` (which takes a lock: a signal arriving while a
handler holds it ran the handler again in the same thread, which then waited on itself for
ever). Waits wake through `signal.set_wakeup_fd` on a non-blocking self-pipe: the interpreter's
C-level handler writes a byte there, and `StopSignals.wait` is a `select` on the pipe.
"""

from __future__ import annotations

import os
import select
import signal
import threading
import time

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

# Set by `up` (processes.Child) in each child's environment: the pid of the parent whose death
# must stop the child. PR_SET_PDEATHSIG delivers SIGTERM when it dies, but a child ignores
# SIGTERM until its entry point installs its handlers (a signal before would be a traceback):
# a parent gone meanwhile is noticed when they are installed (`stop_signals`).
PARENT_PID_ENV = "MAPF_FLEET_PARENT_PID"

# Longest time a wait goes without looking at the flag: the wake-up fd is the process's one
# and a library may take it over (then a wait notices a stop within this).
_SLICE_S = 0.5


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


class _WakeupPipe:
    """The process's self-pipe, created once (a fork inherits it: the child makes its own)."""

    def __init__(self):
        self.pid = -1
        self.read_fd = self.write_fd = -1

    def fds(self) -> tuple[int, int]:
        if self.pid != os.getpid():
            self.read_fd, self.write_fd = os.pipe()
            for fd in (self.read_fd, self.write_fd):
                os.set_blocking(fd, False)
                os.set_inheritable(fd, False)
            self.pid = os.getpid()
        return self.read_fd, self.write_fd

    def drain(self) -> None:
        try:
            while os.read(self.read_fd, 4096):
                pass
        except (BlockingIOError, InterruptedError, OSError):
            pass


_PIPE = _WakeupPipe()


class StopSignals:
    """SIGINT / SIGTERM (`signals`) -> a stop request: `requested`, the first signal in
    `signum`, how many in `count`; `forced` from the second. Install in the main thread
    (`with StopSignals() as signals:` or `.install()`); `restore()` brings back the previous
    handlers and wake-up fd. `wait(seconds)` sleeps until a stop or the time is up."""

    def __init__(self, signals=STOP_SIGNALS):
        self.signals = tuple(signals)
        self.signum: int | None = None
        self.count = 0
        self._previous: dict = {}
        self._previous_wakeup: int | None = None

    # -- installing ---------------------------------------------------------------------------
    def install(self) -> "StopSignals":
        """Catch the signals (main thread only; elsewhere a no-op). Installing again over
        handlers set since (e.g. by `ray.init`) is `reinstall()`."""
        if threading.current_thread() is threading.main_thread() and not self._previous:
            self._catch()
        return self

    def reinstall(self) -> None:
        """This object's handler again over whatever was installed since (main thread);
        `restore()` still brings back the handlers from before the first install."""
        if threading.current_thread() is not threading.main_thread():
            return
        if not self._previous:
            self._catch()
            return
        for sig in self.signals:
            signal.signal(sig, self._handle)
        _, write_fd = _PIPE.fds()
        signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)

    def _catch(self) -> None:
        _, write_fd = _PIPE.fds()
        for sig in self.signals:
            self._previous[sig] = signal.signal(sig, self._handle)
        self._previous_wakeup = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)

    @property
    def installed(self) -> bool:
        return bool(self._previous)

    def restore(self) -> None:
        if not self._previous:
            return
        for sig, previous in self._previous.items():
            signal.signal(sig, previous if previous is not None else signal.SIG_DFL)
        self._previous.clear()
        if self._previous_wakeup is not None:
            try:
                signal.set_wakeup_fd(self._previous_wakeup)
            except ValueError:  # that fd is closed by now
                signal.set_wakeup_fd(-1)
            self._previous_wakeup = None

    def __enter__(self) -> "StopSignals":
        return self.install()

    def __exit__(self, *exc) -> None:
        self.restore()

    # -- the handler: attribute assignments only (it may run inside itself) -----------------------
    def _handle(self, signum, frame) -> None:
        if self.signum is None:
            self.signum = int(signum)
        self.count += 1

    def request(self, signum: int = signal.SIGTERM) -> None:
        """A stop request as if `signum` had come (e.g. the parent is gone)."""
        self._handle(signum, None)

    # -- what the process acts on ---------------------------------------------------------------
    @property
    def requested(self) -> bool:
        return self.signum is not None

    def is_set(self) -> bool:  # the threading.Event spelling (`signals.event.is_set()`)
        return self.requested

    @property
    def event(self) -> "StopSignals":
        """Itself: `is_set()` and `wait(timeout)` as on the Event it used to be."""
        return self

    def wait(self, seconds: float | None = None) -> bool:
        """Sleep up to `seconds` (None: until a stop); True when a stop signal came. Wakes at
        once on a signal (the self-pipe), from any thread."""
        deadline = None if seconds is None else time.monotonic() + max(0.0, float(seconds))
        read_fd, _ = _PIPE.fds()
        main = threading.current_thread() is threading.main_thread()
        while not self.requested:
            left = _SLICE_S if deadline is None else min(_SLICE_S, deadline - time.monotonic())
            if left <= 0:
                return False
            try:
                ready, _, _ = select.select([read_fd], [], [], left)
            except (OSError, ValueError):
                time.sleep(min(left, 0.05))
                continue
            if ready and not self.requested:
                if main:  # another signal's byte (the Python handlers run in this thread)
                    _PIPE.drain()
                else:  # the main thread drains; a stop shows in the flag meanwhile
                    time.sleep(min(left, 0.05))
        return True

    @property
    def forced(self) -> bool:
        """A second signal: stop waiting for a clean end."""
        return self.count >= 2

    @property
    def exit_code(self) -> int | None:
        """128 + the first signal (130 SIGINT, 143 SIGTERM), None without a signal."""
        return None if self.signum is None else 128 + self.signum

    @property
    def name(self) -> str:
        return "" if self.signum is None else signal_name(self.signum)


_PROCESS_SIGNALS: StopSignals | None = None


def parent_gone(environ=None) -> bool:
    """Whether the parent named in PARENT_PID_ENV (set by `up` for its children) is no longer
    this process's parent (it died: the child was re-parented)."""
    environ = os.environ if environ is None else environ
    try:
        expected = int(environ.get(PARENT_PID_ENV, ""))
    except ValueError:
        return False
    return os.getppid() != expected


def stop_signals() -> StopSignals:
    """The process's `StopSignals`, installed on the first call (from the main thread): a
    process's entry point calls it first thing, so a signal that comes while it is still
    importing or loading is kept and acted on as soon as its loop runs. A child of `up` whose
    parent died before this (its SIGTERM ignored meanwhile) gets a stop request (SIGTERM)."""
    global _PROCESS_SIGNALS
    if _PROCESS_SIGNALS is None or not _PROCESS_SIGNALS.installed:
        _PROCESS_SIGNALS = StopSignals().install()
        if parent_gone():
            _PROCESS_SIGNALS.request(signal.SIGTERM)
        os.environ.pop(PARENT_PID_ENV, None)  # not for this process's own children
    return _PROCESS_SIGNALS
