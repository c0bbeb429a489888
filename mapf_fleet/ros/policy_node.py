"""PolicyNode: one robot's learned policy. Builds its own FOV observation from /fleet/map and the
fleet state, talks to its peers (DHC: hidden vectors over a shared topic, two rounds; DCC:
requests and replies as ROS services, with an announcement topic so receivers know how many
requests to await), and publishes its move for the tick and its next waypoint.

Every peer message carries (episode, tick); a message of an older tick is stale and ignored. A
peer missing after `comm_timeout` is left out and reported in the move (missing_peers). A node
started mid-run joins at the newest tick it receives (with a fresh recurrent state).
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from mapf_fleet_interfaces.msg import DccAnnounce, DhcHidden, FleetState, RobotMove, RobotStatus
from mapf_fleet_interfaces.srv import DccMessage
from nav_msgs.msg import OccupancyGrid
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node

from mapf_fleet.grid.actions import ACTION_DELTAS
from mapf_fleet.ros import common
from mapf_fleet.ros.mailbox import Mailbox
from mapf_fleet.ros.robot_logic import RobotBrain

PARAMETERS = {
    "robot_id": (0, "index of this robot in the fleet state"),
    "checkpoint": ("", "checkpoint file (mapf_fleet.models.save_checkpoint) to run"),
    "comm_timeout": (2.0, "seconds to wait for a peer's message before leaving it out"),
    "service_timeout": (2.0, "seconds to wait for a peer's DCC service to be discovered"),
    "status_period": (0.5, "seconds between readiness heartbeats"),
}


def load_policy_model(path: str):
    import torch

    from mapf_fleet.models.checkpoint import load_checkpoint

    torch.set_num_threads(1)  # many robots share the cores: one thread each
    model, metadata = load_checkpoint(path)
    return model.eval(), metadata


class PolicyNode(Node):
    def __init__(self, robot_id: int | None = None, checkpoint: str | None = None, model=None,
                 **node_kwargs):
        overrides = list(node_kwargs.pop("parameter_overrides", None) or [])
        if robot_id is not None or checkpoint is not None:
            from rclpy.parameter import Parameter

            if robot_id is not None:
                overrides.append(Parameter("robot_id", value=int(robot_id)))
            if checkpoint is not None:
                overrides.append(Parameter("checkpoint", value=str(checkpoint)))
        name = f"mapf_policy_{robot_id}" if robot_id is not None else "mapf_policy"
        super().__init__(name, parameter_overrides=overrides, **node_kwargs)
        for pname, (default, text) in PARAMETERS.items():
            self.declare_parameter(pname, default, ParameterDescriptor(description=text))
        self.robot_id = int(self.get_parameter("robot_id").value)
        if self.robot_id < 0:
            raise ValueError(f"robot_id must be >= 0, got {self.robot_id}")
        self.comm_timeout = float(self.get_parameter("comm_timeout").value)
        self.service_timeout = float(self.get_parameter("service_timeout").value)
        if model is None:
            path = self.get_parameter("checkpoint").value
            if not path:
                raise ValueError("parameter 'checkpoint' is required (a checkpoint file path)")
            model, _ = load_policy_model(path)
        self.brain = RobotBrain(model, self.robot_id, model.config.obs_radius)
        self.algo = self.brain.algo
        self.mailbox = Mailbox()
        self.grid = None
        self.geometry = None
        self._state_cond = threading.Condition()
        self._latest_state: FleetState | None = None
        self._episode = None
        self._tick = -1
        self._stop = threading.Event()
        self._clients: dict[tuple[str, int], object] = {}
        self.decisions = 0
        group = ReentrantCallbackGroup()

        self.create_subscription(OccupancyGrid, common.MAP_TOPIC, self._on_map,
                                 common.latched_qos(), callback_group=group)
        self.create_subscription(FleetState, common.STATE_TOPIC, self._on_state,
                                 common.reliable_qos(10), callback_group=group)
        self.move_pub = self.create_publisher(RobotMove, common.MOVES_TOPIC, common.reliable_qos(100))
        self.waypoint_pub = self.create_publisher(PoseStamped, common.waypoint_topic(self.robot_id),
                                                  common.reliable_qos(10))
        self.status_pub = self.create_publisher(RobotStatus, common.STATUS_TOPIC,
                                                common.reliable_qos(100))
        if self.algo == "dhc":
            self.peer_pub = self.create_publisher(DhcHidden, common.DHC_HIDDEN_TOPIC,
                                                  common.reliable_qos(1000))
            self.create_subscription(DhcHidden, common.DHC_HIDDEN_TOPIC, self._on_hidden,
                                     common.reliable_qos(1000), callback_group=group)
        else:
            self.peer_pub = self.create_publisher(DccAnnounce, common.DCC_ANNOUNCE_TOPIC,
                                                  common.reliable_qos(1000))
            self.create_subscription(DccAnnounce, common.DCC_ANNOUNCE_TOPIC, self._on_announce,
                                     common.reliable_qos(1000), callback_group=group)
            self.create_service(DccMessage, common.dcc_request_service(self.robot_id),
                                self._on_dcc_request, callback_group=group)
            self.create_service(DccMessage, common.dcc_reply_service(self.robot_id),
                                self._on_dcc_reply, callback_group=group)
        self.create_timer(float(self.get_parameter("status_period").value), self._heartbeat,
                          callback_group=group)
        self._thread = threading.Thread(target=self._loop, name=f"policy-{self.robot_id}",
                                        daemon=True)

    # ---- callbacks: store and notify, never block ----
    def _on_map(self, msg):
        self.grid, self.geometry = common.occupancy_to_grid(msg)

    def _on_state(self, msg: FleetState):
        with self._state_cond:
            # keep only the newest: a slow or restarted node skips to the current tick
            self._latest_state = msg
            self._state_cond.notify_all()

    def _on_hidden(self, msg: DhcHidden):
        self.mailbox.put(msg.episode, f"dhc{msg.round}", msg.tick, msg.robot_id,
                         np.asarray(msg.hidden, dtype=np.float32))

    def _on_announce(self, msg: DccAnnounce):
        self.mailbox.put(msg.episode, "announce", msg.tick, msg.robot_id,
                         [int(t) for t in msg.targets])

    def _on_dcc_request(self, request, response):
        response.accepted = self.mailbox.put(request.episode, "request", request.tick,
                                             request.sender, np.asarray(request.hidden, np.float32))
        return response

    def _on_dcc_reply(self, request, response):
        response.accepted = self.mailbox.put(request.episode, "reply", request.tick,
                                             request.sender, np.asarray(request.hidden, np.float32))
        return response

    def _heartbeat(self):
        peers = self.peer_pub.get_subscription_count()
        self.status_pub.publish(RobotStatus(
            episode=self._episode or 0, robot_id=self.robot_id, tick=max(self._tick, 0),
            ready=self.grid is not None, peers=peers,
            detail=f"{self.algo}, {self.decisions} decisions, "
                   f"{self.mailbox.stale_dropped} stale messages ignored"))

    # ---- the decision loop (own thread) ----
    def start(self):
        self._thread.start()

    def stop(self):
        self._stop.set()
        with self._state_cond:
            self._state_cond.notify_all()
        self.mailbox.interrupt()
        self._thread.join(5.0)

    def _loop(self):
        while not self._stop.is_set():
            with self._state_cond:
                while not self._stop.is_set() and (
                        self._latest_state is None or self.grid is None or
                        (self._latest_state.episode == self._episode and
                         self._latest_state.tick <= self._tick)):
                    self._state_cond.wait(0.2)
                if self._stop.is_set():
                    return
                state = self._latest_state
            try:
                self._decide(state)
            except Exception as exc:  # a bad tick must not kill the robot
                self.get_logger().error(f"tick {state.tick}: decision failed: {exc!r}")
                self._tick = state.tick

    def _decide(self, state: FleetState):
        if state.episode != self._episode:
            self._episode = state.episode
            self.brain.reset()
        elif state.tick != self._tick + 1:
            # joined mid-run (restart) or skipped ticks: the recurrent state is not ours anymore
            self.brain.reset()
        self._tick = tick = int(state.tick)
        self.mailbox.set_tick(state.episode, tick)
        if state.done:
            return
        positions = np.stack([np.asarray(state.rows), np.asarray(state.cols)], 1).astype(np.int64)
        goals = np.stack([np.asarray(state.goal_rows), np.asarray(state.goal_cols)], 1).astype(np.int64)
        if self.robot_id >= len(positions):
            raise ValueError(f"robot_id {self.robot_id} not in a fleet of {len(positions)} robots")
        last_actions = np.asarray(state.last_actions, dtype=np.int64)
        self.brain.begin_tick(self.grid, positions, goals, last_actions)
        missing = self._communicate_dhc(tick) if self.algo == "dhc" else self._communicate_dcc(tick)
        if self.mailbox.current_tick != tick:
            return  # the fleet moved on while we waited: this decision is stale
        action = self.brain.decide()
        self.decisions += 1
        self.move_pub.publish(RobotMove(episode=state.episode, tick=tick, robot_id=self.robot_id,
                                        action=action, missing_peers=sorted(missing)))
        target = positions[self.robot_id] + ACTION_DELTAS[action]
        self.waypoint_pub.publish(common.cell_pose(target[0], target[1], self.geometry,
                                                   self.get_clock().now().to_msg()))

    def _deadline(self):
        return time.monotonic() + self.comm_timeout

    def _communicate_dhc(self, tick: int) -> set[int]:
        missing: set[int] = set()
        partners = self.brain.dhc_partners()
        for r in range(self.brain.model.config.comm_rounds):
            self.peer_pub.publish(DhcHidden(
                episode=self._episode, tick=tick, round=r, robot_id=self.robot_id,
                hidden=self.brain.message.numpy().astype(np.float32).tolist()))
            received = self.mailbox.wait_for(f"dhc{r}", tick, partners, self._deadline())
            missing.update(set(partners) - set(received))
            self.brain.dhc_round(r, received)
        if missing:
            self.get_logger().warning(f"tick {tick}: left out partners {sorted(missing)}")
        return missing

    def _communicate_dcc(self, tick: int) -> set[int]:
        missing: set[int] = set()
        targets = self.brain.dcc_targets()
        neighbours = self.brain.fov_neighbours()
        self.peer_pub.publish(DccAnnounce(episode=self._episode, tick=tick,
                                          robot_id=self.robot_id, targets=targets))
        hidden = self.brain.message.numpy().astype(np.float32).tolist()
        for j in targets:
            self._send("request", j, tick, hidden)
        # Requesters of this robot are among its FOV neighbours (the FOV is symmetric): their
        # announcements tell how many requests to await.
        announced = self.mailbox.wait_for("announce", tick, neighbours, self._deadline())
        missing.update(set(neighbours) - set(announced))
        requesters = [i for i, t in announced.items() if self.robot_id in t]
        requests = self.mailbox.wait_for("request", tick, requesters, self._deadline())
        missing.update(set(requesters) - set(requests))
        self.brain.dcc_absorb_requests(requests)
        reply = self.brain.message.numpy().astype(np.float32).tolist()
        for i in requests:
            self._send("reply", i, tick, reply)
        replies = self.mailbox.wait_for("reply", tick, targets, self._deadline())
        missing.update(set(targets) - set(replies))
        self.brain.dcc_absorb_replies(replies)
        if missing:
            self.get_logger().warning(f"tick {tick}: left out peers {sorted(missing)}")
        return missing

    def _send(self, kind: str, peer: int, tick: int, hidden) -> None:
        """Fire-and-forget DCC service call: the receiver only stores it, so nobody blocks
        inside a callback and the protocol cannot deadlock; timeouts bound every wait."""
        key = (kind, int(peer))
        client = self._clients.get(key)
        if client is None:
            name = (common.dcc_request_service if kind == "request" else
                    common.dcc_reply_service)(peer)
            client = self.create_client(DccMessage, name)
            self._clients[key] = client
        if not client.service_is_ready() and not client.wait_for_service(self.service_timeout):
            self.get_logger().warning(f"tick {tick}: {kind} service of robot {peer} not found")
            return
        offset = self.brain.positions[self.robot_id] - self.brain.positions[peer]
        client.call_async(DccMessage.Request(
            episode=self._episode, tick=tick, sender=self.robot_id,
            rel_row=int(offset[0]), rel_col=int(offset[1]), hidden=hidden))


def spin_policy_nodes(nodes: list[PolicyNode], until=None) -> None:
    """Spin nodes (one or many in this process) until `until()` is true or Ctrl-C."""
    executor = (SingleThreadedExecutor() if len(nodes) == 1 else
                MultiThreadedExecutor(num_threads=min(8, 2 + len(nodes))))
    for node in nodes:
        executor.add_node(node)
    spinner = common.SpinThread(executor).start()
    for node in nodes:
        node.start()
    try:
        while rclpy.ok() and not (until and until()):
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        for node in nodes:
            node.stop()
        spinner.stop()
        for node in nodes:
            node.destroy_node()


def main(argv: list[str] | None = None) -> int:
    common.prepare_environment()
    args = sys.argv if argv is None else ["policy"] + list(argv)
    rclpy.init(args=args)
    try:
        node = PolicyNode()
        spin_policy_nodes([node])
    finally:
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
