"""A thread-safe mailbox for the messages of lockstep ticks (no rclpy, unit-testable).

ROS callbacks `put` messages keyed by (kind, tick, sender); the node's decision thread `wait_for`
the senders it needs until a deadline. Messages of a tick older than the current one are stale:
they are dropped and counted, never used. Messages of a later tick are kept, because a faster
peer may already be there.
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict


class Mailbox:
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
