"""`mapf-fleet goal` asks again when a reply is lost (a service reply sent before the server
matched the client's reply reader: seen while the machine was loaded), but never queues tasks
twice: once the fleet's goal events show the request arrived, it stops asking."""

from __future__ import annotations

from mapf_fleet.ros.goal_cli import _ask


class _Future:
    def __init__(self, answered: bool):
        self.answered = answered

    def done(self) -> bool:
        return self.answered


def test_a_lost_reply_is_asked_again_within_the_timeout():
    sent = []

    def send():
        sent.append(_Future(answered=len(sent) == 2))  # the first two replies are lost
        return sent[-1]

    future = _ask(send, timeout=6.0, signals=None, attempts=4)
    assert future is sent[2] and len(sent) == 3


def test_no_answer_gives_up_at_the_timeout_and_stop_ends_the_asking():
    sent = []

    def send():
        sent.append(_Future(answered=False))
        return sent[-1]

    assert _ask(send, timeout=2.0, signals=None, attempts=2) is None and len(sent) == 2
    sent.clear()
    assert _ask(send, timeout=4.0, signals=None, attempts=4, stop=lambda: True) is None
    assert len(sent) == 1  # the request arrived (goal events): not sent twice
