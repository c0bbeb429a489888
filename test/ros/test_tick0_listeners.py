"""Tick 0 starts only once everyone who must hear it is matched (issue 40):

- the bag recorder of `up --bag` (mapf_fleet/ros/bag.py) subscribes to the fleet state, which
  tick 0 waits for (the simulator's `state_recorder`), only once it has matched every expected
  publisher (each policy process's /fleet/move_batches), or after its timeout, saying which
  were missing; a bag of a run whose recorder heard the state before it matched every hub lost
  that hub's first batches (test_fleet_move_batches.py shows it end to end);
- the aggregator (real-robot mode) starts tick 0 only once every process whose robots reported
  ready hears the fleet state, as the simulator does (it used to wait only for the poses and
  the heartbeats: a hub not yet matched to the state's publisher missed tick 0).

In-process nodes in the test's own domain (loopback only: ros_env, test/conftest.py)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
INSTANCE = REPO / "config" / "fleet" / "instance_small.yaml"


def _wait(condition, timeout: float, step: float = 0.05, tick=lambda: None) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        tick()
        if condition():
            return True
        time.sleep(step)
    return condition()


def _spin(*nodes):
    from rclpy.executors import SingleThreadedExecutor

    from mapf_fleet.ros.common import SpinThread

    executor = SingleThreadedExecutor()
    for node in nodes:
        executor.add_node(node)
    return SpinThread(executor).start()


def _recorder_subscribes(node, topic: str) -> bool:
    from mapf_fleet.ros.bag import RECORDER_NODE

    return any(e.node_name == RECORDER_NODE for e in node.get_subscriptions_info_by_topic(topic))


@pytest.mark.ros
def test_the_recorder_subscribes_to_the_state_only_once_every_hub_is_matched(
        tmp_path, rclpy_context):
    import rclpy
    from mapf_fleet_interfaces.msg import FleetState, RobotMoves

    from mapf_fleet.ros import common
    from mapf_fleet.ros.bag import RECORDER_NODE, BagRecorder

    recorder_node = rclpy.create_node(RECORDER_NODE)
    fleet = rclpy.create_node("fake_fleet")
    state_pub = fleet.create_publisher(FleetState, common.STATE_TOPIC, common.reliable_qos(10))
    hubs = [fleet.create_publisher(RobotMoves, common.MOVE_BATCHES_TOPIC,
                                   common.reliable_qos(100))]
    recorder = BagRecorder(recorder_node, tmp_path / "bag",
                           expect={common.MOVE_BATCHES_TOPIC: 2}, expect_timeout=60.0)
    spinner = _spin(recorder_node, fleet)
    try:
        # one hub of two: the recorder waits, and the fleet sees no recorder on the state
        assert _wait(lambda: recorder.unmatched() == [
            f"{common.MOVE_BATCHES_TOPIC} (1 of 2 publishers matched)"], 20.0), \
            recorder.unmatched()
        time.sleep(1.0)
        assert not recorder.ready and not _recorder_subscribes(fleet, common.STATE_TOPIC)
        assert state_pub.get_subscription_count() == 0
        # the second hub: ready, the state subscribed (what tick 0 waits for), and matched
        hubs.append(fleet.create_publisher(RobotMoves, common.MOVE_BATCHES_TOPIC,
                                           common.reliable_qos(100)))
        assert _wait(lambda: recorder.ready, 20.0), recorder.unmatched()
        assert recorder.unmatched() == []
        assert _wait(lambda: state_pub.get_subscription_count() == 1, 20.0)
        assert _recorder_subscribes(fleet, common.STATE_TOPIC)
        # tick 0 now: the state and both hubs' batches reach the bag
        assert _wait(lambda: all(h.get_subscription_count() for h in hubs), 20.0)
        state_pub.publish(FleetState(tick=0))
        for k, hub in enumerate(hubs):
            hub.publish(RobotMoves(tick=0, robot_ids=[k]))
        assert _wait(lambda: recorder.counts.get(common.STATE_TOPIC) == 1
                     and recorder.counts[common.MOVE_BATCHES_TOPIC] == 2, 20.0), recorder.counts
    finally:
        spinner.stop()
        recorder.close()
        fleet.destroy_node()
        recorder_node.destroy_node()


@pytest.mark.ros
def test_the_recorder_subscribes_to_the_state_after_its_timeout_saying_what_is_missing(
        tmp_path, rclpy_context):
    import rclpy
    from mapf_fleet_interfaces.msg import RobotMoves

    from mapf_fleet.ros import common
    from mapf_fleet.ros.bag import RECORDER_NODE, BagRecorder

    recorder_node = rclpy.create_node(RECORDER_NODE)
    fleet = rclpy.create_node("fake_fleet")
    hub = fleet.create_publisher(RobotMoves, "/fleet_a/fleet/move_batches",  # noqa: F841
                                 common.reliable_qos(100))
    logged = []
    started = time.monotonic()
    recorder = BagRecorder(recorder_node, tmp_path / "bag", namespace="/fleet_a",
                           expect={"/fleet_a/fleet/move_batches": 3}, expect_timeout=1.5,
                           log=logged.append)
    spinner = _spin(recorder_node, fleet)
    try:
        assert _wait(lambda: recorder.ready, 20.0)
        assert time.monotonic() - started >= 1.5
        assert _wait(lambda: _recorder_subscribes(fleet, "/fleet_a/fleet/state"), 20.0)
        assert len(logged) == 1 and "after 1.5 s" in logged[0] and \
            "/fleet_a/fleet/move_batches (1 of 3 publishers matched)" in logged[0], logged
    finally:
        spinner.stop()
        recorder.close()
        fleet.destroy_node()
        recorder_node.destroy_node()


def test_expected_publishers_are_checked_before_the_bag_is_made(tmp_path, capsys):
    from mapf_fleet.ros import bag

    for expect, problem in (({"/fleet/state": 1}, "the fleet state is what tick 0 waits for"),
                            ({"/fleet/nope": 1}, "not a topic this recorder records"),
                            ({"/fleet/move_batches": 0}, "a count below 1")):
        with pytest.raises(bag.RecordError, match=problem):
            bag.BagRecorder(None, tmp_path / "bag", expect=expect)
        assert not (tmp_path / "bag").exists()
    for argv, problem in ((["--expect", "/fleet/move_batches"], "give TOPIC=COUNT"),
                          (["--expect", "fleet/move_batches=2"], "give TOPIC=COUNT"),
                          (["--expect", "/fleet/move_batches=0"], "give TOPIC=COUNT"),
                          (["--expect-timeout", "0"], "--expect-timeout must be > 0")):
        with pytest.raises(SystemExit) as exc:
            bag.main([str(tmp_path / "bag2"), *argv])
        assert exc.value.code == 2 and problem in capsys.readouterr().err, argv
    assert not (tmp_path / "bag2").exists()


def test_up_expects_every_policy_process_moves_publisher():
    from types import SimpleNamespace

    from mapf_fleet.ros.launcher import recorder_expectations

    def plan(namespace="", per_robot=False):
        return SimpleNamespace(namespace=namespace,
                               policy={"per_robot_messages": per_robot})

    args = SimpleNamespace(single_process=False, nodes_per_process=3)
    assert recorder_expectations(7, plan(), args) == {"/fleet/move_batches": 3,
                                                      "/fleet/progress": 1}
    assert recorder_expectations(6, plan("/fleet_a", per_robot=True), args) == {
        "/fleet_a/fleet/moves": 2, "/fleet_a/fleet/progress": 1}
    single = SimpleNamespace(single_process=True, nodes_per_process=1)
    assert recorder_expectations(8, plan(), single)["/fleet/move_batches"] == 1


@pytest.mark.ros
def test_the_aggregator_starts_tick_0_only_once_every_ready_process_hears_the_state(
        rclpy_context):
    import rclpy
    from mapf_fleet_interfaces.msg import FleetState, HubStatus
    from geometry_msgs.msg import PoseStamped
    from rclpy.parameter import Parameter

    from mapf_fleet.fleet.instances import load_instance_yaml
    from mapf_fleet.ros import common
    from mapf_fleet.ros.aggregator_node import WAIT_LOG_PERIOD_S, FleetStateAggregator

    instance = load_instance_yaml(INSTANCE)
    n = instance.num_agents
    aggregator = FleetStateAggregator(parameter_overrides=[
        Parameter("instance_file", value=str(INSTANCE)),
        Parameter("startup_timeout", value=60.0), Parameter("max_steps", value=2),
        Parameter("decision_timeout", value=0.2), Parameter("arrival_timeout", value=0.2)])
    robots = rclpy.create_node("fake_robots_and_hub")
    status_pub = robots.create_publisher(HubStatus, common.HUB_STATUS_TOPIC,
                                         common.reliable_qos(100))
    pose_pubs = [robots.create_publisher(PoseStamped, common.pose_topic(i),
                                         common.reliable_qos(10)) for i in range(n)]
    poses = [common.cell_pose(int(r), int(c), aggregator.geometry) for r, c in instance.starts]

    def feed():  # every robot at its start; one process hosting them all, ready
        for pub, pose in zip(pose_pubs, poses):
            pub.publish(pose)
        status_pub.publish(HubStatus(episode=0, ready=True, peers=n, host="fake_host",
                                     robot_ids=list(range(n))))

    states = []
    spinner = _spin(aggregator, robots)
    aggregator.start()
    try:
        # posed and ready, but the process's state subscription is not there (not matched)
        assert _wait(lambda: (aggregator.positions[:, 0] >= 0).all()
                     and not aggregator.ticker.unready(), 30.0, 0.1, feed)
        # past a period of its waiting log: its wait of a period once ended the start-up wait
        _wait(lambda: False, WAIT_LOG_PERIOD_S + 1.0, 0.1, feed)
        assert aggregator.run is None, "tick 0 started before the ready process heard the state"
        robots.create_subscription(FleetState, common.STATE_TOPIC, states.append,
                                   common.reliable_qos(10))
        assert _wait(lambda: any(s.tick == 0 for s in states), 30.0, 0.1, feed), \
            "tick 0 never came once the process heard the state"
        assert aggregator.run is not None
    finally:
        aggregator.ticker.stop()
        aggregator.finished.wait(20.0)
        spinner.stop()
        for node in (aggregator.goals.node, aggregator, robots):
            node.destroy_node()
