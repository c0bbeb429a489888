"""The arbiter's intake of a policy process's batched messages, without ROS (issue 40, Scale:
one message per policy process per tick instead of one per robot): a RobotMoves carries every
hosted robot's decision with the numbers of the robots' own RobotMove, a HubStatus every hosted
robot's heartbeat; a malformed batch is refused in one line naming the field, bad moves inside
a batch are refused one by one, stale batches are dropped."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from mapf_fleet.fleet.lockstep import FleetTicker


def _batch(robots, rankings, tick=0, episode=9, requested=None, received=None, missing=None):
    requested = requested or [[] for _ in robots]
    missing = missing or [[] for _ in robots]
    return SimpleNamespace(
        episode=episode, tick=tick, host="hub_a", robot_ids=list(robots),
        preferences=[a for r in rankings for a in r],
        messages_received=list(received or [0] * len(robots)),
        requested_counts=[len(r) for r in requested], requested=[j for r in requested for j in r],
        missing_counts=[len(m) for m in missing], missing_peers=[j for m in missing for j in m])


def _move(robot, ranking, requested=(), received=0, missing=()):
    return SimpleNamespace(episode=9, tick=0, robot_id=robot, action=ranking[0],
                           preferences=list(ranking), requested=list(requested),
                           messages_received=received, missing_peers=list(missing))


RANKINGS = [[2, 0, 1, 3, 4], [4, 3, 2, 1, 0], [0, 1, 2, 3, 4], [1, 0, 2, 3, 4]]
REQUESTED = [[1, 3], [], [0], [2, 1, 0]]
RECEIVED = [4, 0, 2, 6]


def test_a_batch_gives_the_decisions_of_the_same_moves_sent_one_by_one():
    one_by_one, batched = FleetTicker(5, episode=9), FleetTicker(5, episode=9)
    for robot in range(4):
        one_by_one.on_move(_move(robot, RANKINGS[robot], REQUESTED[robot], RECEIVED[robot]))
    # two processes' batches, robots in any order
    assert batched.on_moves(_batch([3, 0], [RANKINGS[3], RANKINGS[0]],
                                   requested=[REQUESTED[3], REQUESTED[0]],
                                   received=[RECEIVED[3], RECEIVED[0]])) is None
    assert batched.on_moves(_batch([1, 2], RANKINGS[1:3], requested=REQUESTED[1:3],
                                   received=RECEIVED[1:3])) is None
    a, b = one_by_one.collect(0.0), batched.collect(0.0)
    np.testing.assert_array_equal(a.rankings, b.rankings)
    np.testing.assert_array_equal(b.actions, [2, 4, 0, 1, 0])
    assert a.requested == b.requested == REQUESTED + [[]]
    assert a.messages == b.messages == RECEIVED + [0]
    assert a.missing == b.missing == [4]


def test_collect_returns_when_the_batches_hold_every_robot():
    ticker = FleetTicker(4, episode=9)
    ticker.on_moves(_batch([0, 1, 2, 3], RANKINGS))
    assert ticker.collect(600.0).missing == []   # no wait for the timeout


def test_stale_and_foreign_batches_are_dropped():
    ticker = FleetTicker(2, episode=9, tick=3)
    assert ticker.on_moves(_batch([0, 1], RANKINGS[:2], tick=2)) is None   # an older tick
    assert ticker.on_moves(_batch([0, 1], RANKINGS[:2], tick=3, episode=8)) is None  # another run
    assert ticker.collect(0.0).missing == [0, 1]


def test_a_malformed_batch_is_refused_in_one_line_naming_the_field():
    ticker = FleetTicker(4, episode=9)
    short = _batch([0, 1], RANKINGS[:2])
    short.preferences = short.preferences[:-1]
    assert "9 preferences for 2 robots" in ticker.on_moves(short)
    counts = _batch([0, 1], RANKINGS[:2], requested=[[1], [0]])
    counts.requested_counts = [1, 2]
    assert "requested_counts sum to 3, 2 requested" in ticker.on_moves(counts)
    received = _batch([0, 1], RANKINGS[:2])
    received.messages_received = [0]
    text = ticker.on_moves(received)
    assert "1 messages_received for 2 robots" in text and "\n" not in text
    missing = _batch([0, 1], RANKINGS[:2], missing=[[1], []])
    missing.missing_peers = []
    assert "missing_counts sum to 1, 0 missing_peers" in ticker.on_moves(missing)
    assert ticker.collect(0.0).missing == [0, 1, 2, 3]   # nothing of them was taken


def test_bad_moves_in_a_batch_are_refused_and_the_others_taken():
    ticker = FleetTicker(3, episode=9)
    text = ticker.on_moves(_batch([0, 1, 7], [RANKINGS[0], [1, 1, 0, 2, 3], RANKINGS[2]]))
    assert "robot 1" in text and "bad move 7/0" in text
    assert ticker.collect(0.0).missing == [1, 2]


def test_robots_that_decided_without_peers_are_reported_in_one_line():
    ticker = FleetTicker(3, episode=9)
    text = ticker.on_moves(_batch([0, 1, 2], RANKINGS[:3], missing=[[2], [], [0, 1]]))
    assert text == "tick 0: robots decided without peers {0: [2], 2: [0, 1]} (timed out)"
    assert ticker.collect(0.0).missing == []


def test_a_hub_status_makes_every_robot_of_its_process_ready():
    ticker = FleetTicker(4, episode=5)
    status = SimpleNamespace(episode=0, robot_ids=[0, 1, 2], ready=True, peers=4, host="a")
    ticker.on_hub_status(status)
    assert ticker.wait_ready(0.05) == [3]
    # a process serving another simulator's run is not ours; one not ready is not ready
    ticker.on_hub_status(SimpleNamespace(episode=77, robot_ids=[3], ready=True, peers=4, host="b"))
    ticker.on_hub_status(SimpleNamespace(episode=5, robot_ids=[3], ready=False, peers=4, host="b"))
    assert ticker.wait_ready(0.05) == [3]
    ticker.on_hub_status(SimpleNamespace(episode=5, robot_ids=[3], ready=True, peers=4, host="b"))
    assert ticker.wait_ready(0.05) == []


def test_the_ticker_counts_the_processes_of_the_ready_robots():
    """The simulator waits until as many processes hear its state as host ready robots (a hub
    with the map and its peers but not yet the state's publisher missed ticks 0 and 1 of a
    1,024-robot run): `ready_hosts` counts them, from batched and per-robot heartbeats."""
    ticker = FleetTicker(5, episode=5)
    ticker.on_hub_status(SimpleNamespace(episode=0, robot_ids=[0, 1], ready=True, peers=5,
                                         host="a"))
    ticker.on_hub_status(SimpleNamespace(episode=0, robot_ids=[2, 3], ready=False, peers=5,
                                         host="b"))
    assert ticker.ready_hosts() == 1
    ticker.on_status(SimpleNamespace(episode=0, robot_id=4, ready=True, peers=5, host="c"))
    ticker.on_hub_status(SimpleNamespace(episode=0, robot_ids=[2, 3], ready=True, peers=5,
                                         host="b"))
    assert ticker.ready_hosts() == 3
