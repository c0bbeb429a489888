"""The exchange's plumbing below the numbers: `Mailbox` (the messages of the tick a process is
at, waited for with a deadline) and `TickTiming` (where a process's tick went: observe, infer,
communicate; logged by every policy process)."""

from __future__ import annotations

import collections
import threading
import time
from collections import defaultdict

import numpy as np

TIMING_EVERY = 50  # the hub logs its per-tick time split every this many decisions

class Mailbox:
    """Messages of lockstep ticks keyed by (kind, tick, sender): the link's deliveries `put`
    them, the deciding thread `wait_for` the senders it needs until a deadline. Messages of a
    tick older than the current one are stale: dropped and counted, never used; messages of a
    later tick are kept, because a faster peer may already be there."""

    def __init__(self):
        self._cond = threading.Condition()
        self._episode = None
        self._current_tick = -1
        self._boxes: dict[tuple, dict[int, object]] = defaultdict(dict)
        self.stale_dropped = 0

    def set_tick(self, episode: int, tick: int) -> None:
        """Enter `tick` of `episode`: older ticks' messages are discarded."""
        with self._cond:
            # Messages that arrived before the node's first state (a faster peer's round 0) are
            # kept when they belong to the episode entered; everything else older goes.
            self._episode = episode
            self._current_tick = tick
            for key in [k for k in self._boxes if k[0] != episode or k[2] < tick]:
                del self._boxes[key]
            self._cond.notify_all()

    @property
    def current_tick(self) -> int:
        return self._current_tick

    def put(self, episode: int, kind: str, tick: int, sender: int, payload) -> bool:
        """Store a message; False (and counted) when it is stale or of another episode."""
        with self._cond:
            if self._episode is not None and episode != self._episode:
                # A message of a newer episode may arrive before the node saw the new state; we
                # cannot tell newer from older here, so only the current episode is accepted.
                self.stale_dropped += 1
                return False
            if tick < self._current_tick:
                self.stale_dropped += 1
                return False
            self._boxes[(episode, kind, tick)][int(sender)] = payload
            self._cond.notify_all()
            return True

    def put_many(self, episode: int, kind: str, tick: int, items) -> int:
        """Store (sender, payload) pairs of one kind and tick at once (one lock, one notify: a
        batched message of a whole process); how many were stored (0 when stale)."""
        items = list(items)
        with self._cond:
            if (self._episode is not None and episode != self._episode) or \
                    tick < self._current_tick:
                self.stale_dropped += len(items)
                return 0
            box = self._boxes[(episode, kind, tick)]
            for sender, payload in items:
                box[int(sender)] = payload
            self._cond.notify_all()
            return len(items)

    def wait_for(self, kind: str, tick: int, senders, deadline: float,
                 count: int | None = None) -> dict[int, object]:
        """Messages of `kind` for `tick`: wait until every sender in `senders` (or, when
        `senders` is None, `count` messages from anyone) arrived or `deadline` (time.monotonic)
        passed; returns what arrived (the caller reports the missing ones)."""
        wanted = None if senders is None else {int(s) for s in senders}
        with self._cond:
            while True:
                box = self._boxes.get((self._episode, kind, tick), {})
                if wanted is not None and wanted.issubset(box.keys()):
                    break
                if wanted is None and count is not None and len(box) >= count:
                    break
                if self._current_tick > tick:  # the fleet moved on: nothing more will come
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cond.wait(remaining)
            box = dict(self._boxes.get((self._episode, kind, tick), {}))
        if wanted is not None:
            box = {s: m for s, m in box.items() if s in wanted}
        return box

    def interrupt(self) -> None:
        with self._cond:
            self._cond.notify_all()


class TickTiming:
    """Where an exchange's tick goes (plain Python), for the hub's log and bench_fleet.py:
    `latency` from the state's stamp to its callback (the simulator's publish and DDS), `wake`
    from the callback to the decision thread, then `observe`, `network` (torch), `send`
    (publishing peer messages, DCC batch calls), `wait` (for the peers' messages) and `moves`
    (ranking, publishing the moves); `begin` a tick, `mark(phase)` at the end of each piece."""

    PHASES = ("latency", "wake", "observe", "network", "send", "wait", "moves")

    def __init__(self):
        self.ticks = 0
        self.total = dict.fromkeys(self.PHASES, 0.0)
        self._tick = dict.fromkeys(self.PHASES, 0.0)
        self._last = None
        self.recent: collections.deque = collections.deque(maxlen=TIMING_EVERY)  # decide s

    def begin(self, started: float, arrived, stamp) -> None:
        self._tick = dict.fromkeys(self.PHASES, 0.0)
        arrived_at, arrived_wall = arrived
        if arrived_at:
            self._tick["wake"] = max(0.0, started - arrived_at)
            sent = stamp.sec + stamp.nanosec * 1e-9
            if sent > 0:
                self._tick["latency"] = max(0.0, arrived_wall - sent)
        self._started = started
        self._last = started

    def mark(self, phase: str) -> None:
        if self._last is None:
            return
        now = time.perf_counter()
        self._tick[phase] += now - self._last
        self._last = now

    def end(self) -> None:
        if self._last is None:
            return
        self.ticks += 1
        for phase, seconds in self._tick.items():
            self.total[phase] += seconds
        self.recent.append(self._last - self._started)
        self._last = None

    def text(self, sent: dict | None = None) -> str:
        n = max(1, self.ticks)
        parts = ", ".join(f"{p} {1000 * self.total[p] / n:.1f}" for p in self.PHASES)
        recent = (f"; last {len(self.recent)} ticks: decide {1000 * np.mean(self.recent):.1f} ms"
                  if self.recent else "")
        counts = (f"; DCC messages local {sent['local']}, to other processes {sent['service']} "
                  f"in {sent['batches']} batch calls, unsent {sent['unsent']}"
                  if sent and (sent["local"] or sent["service"] or sent["unsent"]) else "")
        return f"hub timing over {self.ticks} ticks, ms per tick: {parts}{recent}{counts}"
