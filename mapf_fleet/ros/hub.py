"""PolicyHub: the ROS plumbing of the policy nodes hosted in one process (subscriptions, the
peer topics, the DCC batch service and its clients, heartbeats, the decision thread) around one
`mapf_fleet.models.exchange.PolicyExchange` (ROS-free: what the robots compute and send).

Every robot keeps its own node (its parameters, its publishers, its DCC services: the ROS
interface does not change with the process layout), but the robots of one process share:
- one subscription each to the map, the fleet state, the peer topic (DHC hidden vectors / DCC
  announcements) and the heartbeats (HubStatus, and RobotStatus from per-robot senders);
- ONE move message per process and tick (RobotMoves: every hosted robot's ranked actions) and
  ONE heartbeat per process and `status_period` (HubStatus), so the arbiter takes (processes)
  messages a tick, not (robots); with `per_robot_messages` each robot's RobotMove and
  RobotStatus instead (the per-robot topics /fleet/moves and /fleet/robot_status);
- one `PolicyExchange` run by one decision thread: the local robots' encode / communication
  rounds / Q-values as batched torch calls, with the numbers of the batched evaluator (same
  padding and masking), messages between robots of the same process straight into its mailbox;
  this hub is its link (`publish_hidden`, `publish_announce`, `send`, `warn`);
- ONE peer message per process and round (DhcHidden, DccAnnounce carry all its robots), so a
  round costs (processes x processes) deliveries, not (robots x processes);
- DCC requests and replies between processes as ONE service call per tick and per pair of
  processes (`DccBatch` on the receiving hub's service `fleet/dcc_hub/<host>`, one client per
  remote hub, created when its first heartbeat names it): at most (processes - 1) calls per
  phase instead of one per robot pair, and no client is created during the run (a client per
  robot pair, created as robots met new peers, grew the executor's wait set and the DDS
  discovery traffic tick after tick until every decision was missed). The per-robot services
  `/robot_<i>/dcc_request` / `dcc_reply` still take messages from anything else.

Each robot publishes its five actions ranked (`coordination.ranking.rank_actions` over its
Q-values, `ranking`, ties broken by `tie_breakers(robot id, tick)`, exactly as the batched
evaluator's shield), not a waypoint: the tick's arbiter (simulator or aggregator) resolves the
moves and commands the robots.

Only `comm_timeout`, `service_timeout`, `status_period`, `per_robot_messages` and `ranking` of
the first hosted node are used.
"""

from __future__ import annotations

import array
import collections
import os
import threading
import time

import numpy as np

from mapf_fleet.fleet.lockstep import EpisodeBinding
from mapf_fleet.models.exchange import PolicyExchange
from mapf_fleet.models.mailbox import TIMING_EVERY
from mapf_fleet.ros import common

BATCH_KINDS = ("request", "reply")  # DccBatch.kind


def dcc_hub_service(host: str) -> str:
    """The batch service of the hub named `host` (its node name, as its heartbeats say)."""
    return f"/fleet/dcc_hub/{host}"


class StateWatch:
    """Notices when the fleet state stops coming (plain Python): after `kill -9` of the
    simulator the policy nodes would otherwise wait without a word. `note(tick, done)` on each
    state received; `silence()` returns a line to log, once per silence of `timeout` s: before
    the first state (since start-up), or mid-run (since the last state of a run not yet done; a
    finished run is expected to go quiet). After a reported silence `note` returns a line saying
    the state is back."""

    def __init__(self, timeout: float = 30.0, now: float | None = None):
        self.timeout = float(timeout)
        self._since = time.monotonic() if now is None else now
        self._tick: int | None = None
        self._done = False
        self._reported = False

    def note(self, tick: int, done: bool, now: float | None = None) -> str | None:
        back = self._reported
        self._since = time.monotonic() if now is None else now
        self._tick, self._done, self._reported = int(tick), bool(done), False
        return f"fleet state received again (tick {tick})" if back else None

    def silence(self, now: float | None = None) -> str | None:
        now = time.monotonic() if now is None else now
        quiet = now - self._since
        if self._reported or self._done or quiet < self.timeout:
            return None
        self._reported = True
        if self._tick is None:
            return (f"no fleet state yet after {quiet:.0f} s: waiting for the simulator (or "
                    f"aggregator) on {common.STATE_TOPIC} in this ROS domain and namespace")
        return (f"no fleet state for {quiet:.0f} s since tick {self._tick}: the simulator (or "
                f"aggregator) stopped or is unreachable; the robots wait")


HEARTBEAT_ROBOTS = 32  # heartbeats per status_period the fleet sends, about (see _heartbeat)


class PolicyHub:
    """The ROS side of one process's robots: subscriptions, heartbeats, the batch service and
    its clients, the decision thread; the numbers are its `models.exchange.PolicyExchange`'s."""

    def __init__(self, nodes, model):
        from mapf_fleet_interfaces.msg import (DccAnnounce, DhcHidden, FleetState, HubStatus,
                                               RobotMove, RobotMoves, RobotStatus)
        from mapf_fleet_interfaces.srv import DccBatch
        from nav_msgs.msg import OccupancyGrid
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.node import Node

        if not nodes:
            raise ValueError("PolicyHub needs at least one policy node")
        ids = [n.robot_id for n in nodes]
        if len(set(ids)) != len(ids):
            raise ValueError(f"PolicyHub: robot ids hosted twice in {ids}")
        self.nodes = list(nodes)
        first = nodes[0]
        # the exchange's numbers; this hub is its ROS link (publish_hidden, publish_announce,
        # send, warn)
        self.exchange = PolicyExchange(model, ids, first.comm_timeout, first.ranking,
                                       self, guidance=first.guidance)
        self.algo = self.exchange.algo
        self.ids = self.exchange.ids
        self.index_of = self.exchange.index_of
        self._ids_array = array.array("I", ids)  # for the batched peer messages
        self.service_timeout = first.service_timeout
        self.per_robot = bool(getattr(first, "per_robot_messages", False))
        self.host = f"mapf_policy_hub_{os.getpid()}_{ids[0]}"
        self.node = Node(self.host)
        self.grid = None
        self.geometry = None
        self._state_cond = threading.Condition()
        self._latest_state = None
        self._state_at = (0.0, 0.0)  # (perf_counter, wall clock) when it arrived
        # the run this hub serves: never a foreign simulator's (lockstep.EpisodeBinding)
        self.binding = EpisodeBinding(first.episode_timeout)
        self._ignored_episodes: set[int] = set()
        self._guidance_warned = False
        self.watch = StateWatch(getattr(first, "episode_timeout", 30.0))
        self._stop = threading.Event()
        self._hosts: dict[int, str] = {}  # robot id -> host, from heartbeats
        self._beats = 0
        self._last_beat = None  # (ready, episode) of the last heartbeats sent
        self._hub_clients: dict[str, object] = {}  # remote host -> client of its batch service
        self._ready_hosts: set[str] = set()  # hosts whose batch service our client has seen
        self._inflight: collections.deque = collections.deque()  # (tick, client, future)
        for node in nodes:
            node.hub = self
        group = self._group = ReentrantCallbackGroup()
        self.node.create_subscription(OccupancyGrid, common.rel(common.MAP_TOPIC), self._on_map,
                                      common.latched_qos(), callback_group=group)
        self._state_sub = self.node.create_subscription(
            FleetState, common.rel(common.STATE_TOPIC), self._on_state, common.reliable_qos(10),
            callback_group=group)
        # heartbeats of every process: batched (HubStatus) and per robot (RobotStatus, from a
        # process with per_robot_messages): whom to send DCC batches to, who is ready
        self.node.create_subscription(RobotStatus, common.rel(common.STATUS_TOPIC),
                                      self._on_status,
                                      common.reliable_qos(1000), callback_group=group)
        self.node.create_subscription(HubStatus, common.rel(common.HUB_STATUS_TOPIC),
                                      self._on_hub_status,
                                      common.reliable_qos(100), callback_group=group)
        quiet = common.quiet_publisher_events()
        # every hosted robot's moves and heartbeats (one publisher each for the process): one
        # message per process (tick, period), or one per robot with per_robot_messages
        if self.per_robot:
            self.move_pub = self.node.create_publisher(
                RobotMove, common.rel(common.MOVES_TOPIC), common.reliable_qos(1000),
                event_callbacks=quiet)
            self.status_pub = self.node.create_publisher(
                RobotStatus, common.rel(common.STATUS_TOPIC), common.reliable_qos(1000),
                event_callbacks=quiet)
        else:
            self.move_pub = self.node.create_publisher(
                RobotMoves, common.rel(common.MOVE_BATCHES_TOPIC), common.reliable_qos(100),
                event_callbacks=quiet)
            self.status_pub = self.node.create_publisher(
                HubStatus, common.rel(common.HUB_STATUS_TOPIC), common.reliable_qos(100),
                event_callbacks=quiet)
        if self.algo == "dhc":
            self.peer_pub = self.node.create_publisher(
                DhcHidden, common.rel(common.DHC_HIDDEN_TOPIC), common.reliable_qos(100),
                event_callbacks=quiet)
            self.node.create_subscription(DhcHidden, common.rel(common.DHC_HIDDEN_TOPIC),
                                          self._on_hidden,
                                          common.reliable_qos(100), callback_group=group)
        else:
            self.peer_pub = self.node.create_publisher(
                DccAnnounce, common.rel(common.DCC_ANNOUNCE_TOPIC), common.reliable_qos(100),
                event_callbacks=quiet)
            self.node.create_subscription(DccAnnounce, common.rel(common.DCC_ANNOUNCE_TOPIC),
                                          self._on_announce, common.reliable_qos(1000),
                                          callback_group=group)
            # every other process may call it twice a tick: the services' default queue (10,
            # keep last) dropped requests with 12 processes (384 robots), and each cost a
            # comm_timeout wait
            self.node.create_service(DccBatch, common.rel(dcc_hub_service(self.host)),
                                     self._on_batch, qos_profile=common.reliable_qos(1000),
                                     callback_group=group)
        self.node.create_timer(first.status_period, self._heartbeat, callback_group=group)
        self._thread = threading.Thread(target=self._loop, name=f"policy-hub-{ids[0]}",
                                        daemon=True)

    @property
    def all_nodes(self):
        return [self.node] + self.nodes

    # ---- callbacks: store and notify, never block ----
    def _on_map(self, msg):
        self.grid, self.geometry = common.occupancy_to_grid(msg)

    def _on_state(self, msg):
        with self._state_cond:
            bound = self.binding.episode
            if not self.binding.accept(msg.episode, msg.done):
                if msg.episode not in self._ignored_episodes:
                    self._ignored_episodes.add(msg.episode)
                    self.node.get_logger().warning(
                        f"ignoring the fleet state of episode {msg.episode}: robots "
                        f"{self.ids.tolist()} serve episode {bound} (another simulator in "
                        f"this namespace? give each fleet its own: up --namespace /NAME)")
                return
            # online guidance follows every state in order (before the decision reads it)
            broken = self.exchange.guidance.online and self.exchange.follow(
                msg.episode, int(msg.tick), self.grid,
                np.stack([np.asarray(msg.rows), np.asarray(msg.cols)], 1))
            if broken and not self._guidance_warned:
                self._guidance_warned = True
                self.node.get_logger().error(
                    f"robots {self.ids.tolist()}: online guidance {self.exchange.guidance} no "
                    f"longer follows the fleet's ({broken}); the rule's moves stay safe, the "
                    f"robots' heuristic channels read the last graph followed")
            self._latest_state = msg  # a slow or restarted hub skips to the newest tick
            self._state_at = (time.perf_counter(), time.time())
            back = self.watch.note(msg.tick, msg.done)
            self._state_cond.notify_all()
        if back:
            self.node.get_logger().info(back)

    def _on_status(self, msg):
        """One robot's heartbeat (a process with per_robot_messages)."""
        self._heard(msg.host, (int(msg.robot_id),))

    def _on_hub_status(self, msg):
        """The heartbeat of every robot of one process."""
        self._heard(msg.host, [int(r) for r in msg.robot_ids])

    def _heard(self, host: str, robots) -> None:
        for robot in robots:
            self._hosts[robot] = host
        if self.algo == "dcc" and host != self.host and host not in self._hub_clients:
            # created when the host is first heard, long before tick 0 (readiness waits for it):
            # never during the run
            from mapf_fleet_interfaces.srv import DccBatch

            self._hub_clients[host] = self.node.create_client(
                DccBatch, common.rel(dcc_hub_service(host)),
                qos_profile=common.reliable_qos(1000), callback_group=self._group)

    def _on_hidden(self, msg):
        """Another process's robots' vectors of one round (ours were delivered locally)."""
        ids = np.frombuffer(msg.robot_ids, dtype=np.uint32)
        dim = int(msg.dim)
        hidden = np.frombuffer(msg.hidden, dtype=np.float32)
        if dim <= 0 or len(hidden) != dim * len(ids):
            self.node.get_logger().warning(f"ignored a malformed DhcHidden (dim {dim}, "
                                           f"{len(ids)} robots, {len(hidden)} values)")
            return
        self.exchange.receive_hidden(msg.episode, msg.tick, msg.round, ids.tolist(),
                                     hidden.reshape(-1, dim))

    def _on_announce(self, msg):
        """Another process's robots' DCC targets of this tick."""
        ids = list(msg.robot_ids)
        counts, targets = list(msg.target_counts), list(msg.targets)
        if len(counts) != len(ids) or sum(counts) != len(targets):
            self.node.get_logger().warning(f"ignored a malformed DccAnnounce ({len(ids)} robots, "
                                           f"{len(counts)} counts, {len(targets)} targets)")
            return
        ends = np.cumsum(counts).tolist()
        self.exchange.receive_announce(msg.episode, msg.tick, ids,
                                       [targets[end - c:end] for c, end in zip(counts, ends)])

    def deliver(self, kind: str, receiver: int, request) -> bool:
        """A DCC service call reached robot `receiver` of this process."""
        return self.exchange.mailbox.put(request.episode, f"{kind}{receiver}", request.tick,
                                request.sender, np.asarray(request.hidden, np.float32))

    def _on_batch(self, request, response):
        """Another hub's requests or replies of one tick for robots of this process."""
        kind = BATCH_KINDS[request.kind] if request.kind < len(BATCH_KINDS) else None
        hidden = np.frombuffer(request.hidden, dtype=np.float32)
        dim = int(request.dim)
        if kind is None or dim <= 0 or len(hidden) != dim * len(request.senders) or \
                len(request.receivers) != len(request.senders):
            self.node.get_logger().warning(f"ignored a malformed DCC batch (kind {request.kind}, "
                                           f"dim {dim}, {len(request.senders)} senders)")
            response.accepted = 0
            return response
        response.accepted = self.exchange.receive(kind, request.episode, request.tick,
                                                  request.senders, request.receivers,
                                                  hidden.reshape(-1, dim))
        return response

    @property
    def ready(self) -> bool:
        """The robots can decide: the map is here and the fleet state's publisher is matched
        (a hub that had the map but not yet the state's publisher missed the first ticks)."""
        return self.grid is not None and self._state_sub.get_publisher_count() > 0

    def peers_reachable(self) -> int:
        """Robots whose heartbeat was heard, provided every host seen also subscribes to our peer
        topic (so nothing we publish is lost) and, for DCC, serves the batch service our client
        of it sees; 0 otherwise."""
        hosts = set(self._hosts.values()) | {self.host}
        matched = self.peer_pub.get_subscription_count()
        if matched < len(hosts):
            return 0
        if self.algo == "dcc" and not all(self._hub_clients[h].service_is_ready()
                                          for h in hosts - {self.host}
                                          if h in self._hub_clients):
            return 0
        return len(self._hosts)

    def _heartbeat(self):
        """Every `status_period`: the hosted robots' heartbeat, one HubStatus for all of them
        (every hub and the simulator take every heartbeat: a message per process and period,
        whatever the fleet's size). With per_robot_messages one RobotStatus per robot, when
        it is their turn: up to HEARTBEAT_ROBOTS robots heard, every period; in a larger fleet
        every (robots heard / HEARTBEAT_ROBOTS) periods, so the whole fleet sends about
        HEARTBEAT_ROBOTS heartbeats per period whatever its size (256 robots at 2 Hz were 4,600
        callbacks a second, enough to delay the fleet state by seconds). A change of readiness
        or episode goes out at once."""
        from mapf_fleet_interfaces.msg import HubStatus, RobotStatus

        detail = (f"{self.algo}, {len(self.nodes)} robots on this host, "
                  f"{self.exchange.decisions} decisions, "
                  f"{self.exchange.mailbox.stale_dropped} stale messages ignored")
        if not self.per_robot:
            self.status_pub.publish(HubStatus(
                episode=self.binding.reported, tick=max(self.exchange.tick, 0),
                ready=self.ready, peers=self.peers_reachable(), host=self.host,
                robot_ids=self._ids_array, detail=detail))
            return
        self._beats += 1
        every = max(1, len(self._hosts) // HEARTBEAT_ROBOTS)
        ready, episode = self.ready, self.binding.reported
        if (ready, episode) == self._last_beat and self._beats % every:
            return
        self._last_beat = (ready, episode)
        peers = self.peers_reachable()
        for node in self.nodes:
            self.status_pub.publish(RobotStatus(
                episode=episode, robot_id=node.robot_id, tick=max(self.exchange.tick, 0),
                ready=ready, peers=peers, host=self.host, detail=detail))

    # ---- the decision loop (own thread) ----
    def start(self):
        self._thread.start()

    def stop(self):
        self._stop.set()
        with self._state_cond:
            self._state_cond.notify_all()
        self.exchange.mailbox.interrupt()
        self._thread.join(5.0)
        if self.exchange.timing.ticks:
            self.node.get_logger().info(self.exchange.timing.text(self.exchange.sent))

    def _loop(self):
        while not self._stop.is_set():
            with self._state_cond:
                while not self._stop.is_set() and (
                        self._latest_state is None or self.grid is None or
                        (self._latest_state.episode == self.exchange.episode and
                         self._latest_state.tick <= self.exchange.tick)):
                    self._state_cond.wait(0.2)
                    silence = self.watch.silence()
                    if silence:
                        self.node.get_logger().warning(f"robots {self.ids.tolist()}: {silence}")
                if self._stop.is_set():
                    return
                state, arrived = self._latest_state, self._state_at
            try:
                self._decide(state, arrived)
            except Exception as exc:  # a bad tick must not kill the robots
                import traceback

                self.node.get_logger().error(f"tick {state.tick}: decision failed: {exc!r}\n"
                                             f"{traceback.format_exc()}")
                self.exchange.enter(state.episode, int(state.tick))  # go on with the next

    def _decide(self, state, arrived=(None, None)):
        started = time.perf_counter()
        exchange = self.exchange
        exchange.enter(state.episode, int(state.tick))
        if state.done:
            return
        positions = np.stack([np.asarray(state.rows), np.asarray(state.cols)], 1).astype(np.int64)
        goals = np.stack([np.asarray(state.goal_rows), np.asarray(state.goal_cols)],
                         1).astype(np.int64)
        decision = exchange.decide(self.grid, positions, goals, state.last_actions, started,
                                   arrived, state.header.stamp)
        if decision is None:
            return  # the fleet moved on while we waited: this decision is stale
        rankings, requested, received, missing = decision[:4]
        tick = exchange.tick
        self._publish_moves(state.episode, tick, rankings, requested, received, missing)
        exchange.timing.mark("moves")
        exchange.timing.end()
        if any(missing):
            left_out = {int(self.ids[m]): sorted(s) for m, s in enumerate(missing) if s}
            self.warn(f"tick {tick}: left out peers {left_out}")
        if exchange.decisions % TIMING_EVERY == 0:
            self.node.get_logger().info(exchange.timing.text(exchange.sent))

    def _publish_moves(self, episode, tick, rankings, requested, received, missing) -> None:
        """The hosted robots' decisions of a tick: one RobotMoves (or, with per_robot_messages,
        a RobotMove per robot)."""
        from mapf_fleet_interfaces.msg import RobotMove, RobotMoves

        if self.per_robot:
            for m, node in enumerate(self.nodes):
                ranking = rankings[m].tolist()
                self.move_pub.publish(RobotMove(
                    episode=episode, tick=tick, robot_id=node.robot_id, action=ranking[0],
                    preferences=ranking, missing_peers=sorted(missing[m]),
                    requested=requested[m], messages_received=received[m]))
            return
        left_out = [sorted(s) for s in missing]
        self.move_pub.publish(RobotMoves(
            episode=episode, tick=tick, host=self.host, robot_ids=self._ids_array,
            preferences=array.array("B", np.asarray(rankings, dtype=np.uint8).tobytes()),
            messages_received=array.array("I", [int(r) for r in received]),
            requested_counts=array.array("I", [len(r) for r in requested]),
            requested=array.array("I", [int(j) for r in requested for j in r]),
            missing_counts=array.array("I", [len(s) for s in left_out]),
            missing_peers=array.array("I", [j for s in left_out for j in s])))

    # ---- the exchange's link: ROS ----
    def warn(self, text: str) -> None:
        self.node.get_logger().warning(text)

    def publish_hidden(self, episode, tick, round_index, ids, vectors) -> None:
        """One DhcHidden with this process's robots' vectors of a round."""
        from mapf_fleet_interfaces.msg import DhcHidden

        self.peer_pub.publish(DhcHidden(episode=episode, tick=tick, round=round_index,
                                        dim=vectors.shape[1], robot_ids=self._ids_array,
                                        hidden=array.array("f", vectors.tobytes())))

    def publish_announce(self, episode, tick, ids, targets) -> None:
        """One DccAnnounce with whom this process's robots request."""
        from mapf_fleet_interfaces.msg import DccAnnounce

        self.peer_pub.publish(DccAnnounce(
            episode=episode, tick=tick, robot_ids=self._ids_array,
            target_counts=array.array("I", [len(t) for t in targets]),
            targets=array.array("I", [j for t in targets for j in t])))

    def send(self, kind: str, episode: int, tick: int, entries) -> tuple[int, int]:
        """DCC messages (sender, receiver, vector) to robots of other processes: one DccBatch
        call of each receiving process's hub service (its host from the heartbeats). (entries
        sent, calls made); the rest had no reachable service (logged)."""
        from mapf_fleet_interfaces.srv import DccBatch

        by_host: dict[str, list] = collections.defaultdict(list)
        for entry in entries:
            by_host[self._hosts.get(entry[1], "")].append(entry)
        sent = calls = 0
        for host, batch in by_host.items():
            client = self._hub_clients.get(host)
            # a graph query, milliseconds in a large fleet's DDS graph: asked until it is
            # ready once (a restarted hub comes back under a new host name and client)
            if client is not None and host not in self._ready_hosts and \
                    client.service_is_ready():
                self._ready_hosts.add(host)
            if client is None or host not in self._ready_hosts:
                self.warn(f"tick {tick}: no DCC service for robots {[e[1] for e in batch]} "
                          f"({'no heartbeat heard' if not host else host}): {kind}s not sent")
                continue
            vectors = np.stack([e[2] for e in batch]).astype(np.float32, copy=False)
            future = client.call_async(DccBatch.Request(
                episode=episode, tick=tick, kind=BATCH_KINDS.index(kind),
                dim=vectors.shape[1], senders=array.array("I", [e[0] for e in batch]),
                receivers=array.array("I", [e[1] for e in batch]),
                hidden=array.array("f", vectors.tobytes())))
            self._inflight.append((tick, client, future))
            sent += len(batch)
            calls += 1
        self._forget_old_calls(tick)
        return sent, calls

    def _forget_old_calls(self, tick: int, keep_ticks: int = 2) -> None:
        """A call whose response never comes (a receiver that died or restarted) would keep its
        future in the client forever: forget those older than `keep_ticks` ticks, so nothing
        grows over a run."""
        while self._inflight and self._inflight[0][0] < tick - keep_ticks:
            _, client, future = self._inflight.popleft()
            if future is not None and not future.done():
                client.remove_pending_request(future)
