"""The policy process's timing line (`models.mailbox.TickTiming.text`, logged by every hub each
TIMING_EVERY decisions) is written after ticks were timed: it raised NameError (numpy not
imported where it moved), which failed that tick's decision in every hub, every 50 ticks, and
the fleet missed the moves of whole processes (issue 40, Scale, 1,024 robots)."""

from __future__ import annotations

from types import SimpleNamespace

from mapf_fleet.models.mailbox import TickTiming


def test_the_timing_line_after_timed_ticks():
    timing = TickTiming()
    for _ in range(3):
        timing.begin(0.0, (None, None), SimpleNamespace(sec=0, nanosec=0))
        timing.mark("observe")
        timing.mark("network")
        timing.end()
    text = timing.text({"local": 2, "service": 5, "batches": 1, "unsent": 0})
    assert text.startswith("hub timing over 3 ticks, ms per tick: latency")
    assert "; last 3 ticks: decide " in text and "to other processes 5 in 1 batch calls" in text
