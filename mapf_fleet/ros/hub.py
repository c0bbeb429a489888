"""PolicyHub: the per-process engine behind the policy nodes hosted in one process, and
HubExchange, the fleet's one per-robot exchange (ROS-free: what the hub computes and sends).

Every robot keeps its own node (its parameters, its publishers, its DCC services: the ROS
interface does not change with the process layout), but the robots of one process share:
- one subscription each to the map, the fleet state, the peer topic (DHC hidden vectors / DCC
  announcements) and the heartbeats;
- one `HubExchange` run by one decision thread: the local robots' encode / communication rounds
  / Q-values as batched torch calls, with the numbers of the batched evaluator (same padding and
  masking), messages between robots of the same process straight into its mailbox;
- ONE peer message per process and round (DhcHidden, DccAnnounce carry all its robots), so a
  round costs (processes x processes) deliveries, not (robots x processes);
- DCC requests and replies between processes as ONE service call per tick and per pair of
  processes (`DccBatch` on the receiving hub's service `fleet/dcc_hub/<host>`, one client per
  remote hub, created when its first heartbeat names it): at most (processes - 1) calls per
  phase instead of one per robot pair, and no client is created during the run (issue 23: a
  client per robot pair, created as robots met new peers, grew the executor's wait set and the
  DDS discovery traffic tick after tick until every decision was missed). The per-robot services
  `/robot_<i>/dcc_request` / `dcc_reply` still take messages from anything else.

Each robot publishes its five actions ranked (`coordination.preferences.rank_actions` over its
Q-values, `preference_mode`, ties broken by `tie_breakers(robot id, tick)`, exactly as the batched
evaluator's shield), not a waypoint: the tick's arbiter (simulator or aggregator) resolves the
moves and commands the robots.

Only `comm_timeout`, `service_timeout`, `status_period` and `preference_mode` of the first hosted
node are used.
"""

from __future__ import annotations

import array
import collections
import os
import threading
import time

import numpy as np
import torch

from mapf_fleet.coordination.preferences import rank_actions, tie_breakers
from mapf_fleet.grid.env import (COST_TO_GO_CHANNEL, cost_to_go_channel, cost_to_go_steps,
                                 observation_channels, pad_distances)
from mapf_fleet.grid.heuristic import cached_distances, cached_heuristic_bits
from mapf_fleet.ros import common
from mapf_fleet.ros.lockstep import EpisodeBinding
from mapf_fleet.ros.mailbox import Mailbox

BATCH_KINDS = ("request", "reply")  # DccBatch.kind


def dcc_hub_service(host: str) -> str:
    """The batch service of the hub named `host` (its node name, as its heartbeats say)."""
    return f"/fleet/dcc_hub/{host}"


class LocalObserver:
    """FOV observations of some robots (the local ones) in a fleet, with the padded static map
    and each robot's heuristic channels (and, for the "cost_to_go" observation, its BFS distance
    map) computed once per (map, goals), from the cache the environment uses. Same layout and
    values as `mapf_fleet.grid.env.observe` (off-map = obstacle, heuristic 0 off the map)."""

    def __init__(self, grid: np.ndarray, goals: np.ndarray, radius: int,
                 observation: str = "paper"):
        grid = np.asarray(grid)
        self.key = (grid.shape, grid.tobytes(), np.asarray(goals).tobytes())
        h, w = grid.shape
        r = self.radius = int(radius)
        self.size = 2 * r + 1
        self.hp, self.wp = h + 2 * r, w + 2 * r
        self.channels = observation_channels(observation)
        self.distances = None
        if observation == "cost_to_go":
            distances = cached_distances(grid, goals)  # (M, H, W), to each robot's goal
            self.distances = pad_distances(distances, r).reshape(len(goals), -1)
        bits = cached_heuristic_bits(grid, goals)  # (M, H, W), bit k = heuristic channel k
        static = np.ones((len(goals), self.hp, self.wp), dtype=np.uint8)
        static[:, r:r + h, r:r + w] = (grid != 0).astype(np.uint8) | (bits << 1)
        self.static = static.reshape(len(goals), -1)
        offsets = np.arange(self.size)
        self.window = (offsets[:, None] * self.wp + offsets[None, :]).reshape(-1)
        self.centre = r * self.wp + r

    def observe(self, positions: np.ndarray, local: np.ndarray) -> np.ndarray:
        """float32 (M, C, S, S) for robots `local` given every robot's `positions` (N, 2)."""
        corners = positions[:, 0] * self.wp + positions[:, 1]  # window corner == cell (padded)
        occupancy = np.zeros(self.hp * self.wp, dtype=np.float32)
        occupancy[corners + self.centre] = 1.0
        windows = corners[local][:, None] + self.window  # (M, S*S)
        m, s2 = windows.shape
        obs = np.empty((m, self.channels, s2), dtype=np.float32)
        obs[:, 0] = occupancy[windows]
        obs[:, 0, s2 // 2] = 0.0  # the robot itself is not in its agent channel
        static = np.take_along_axis(self.static, windows, axis=1)
        for bit in range(5):
            obs[:, 1 + bit] = (static >> bit) & 1
        if self.distances is not None:
            distances = np.take_along_axis(self.distances, windows, axis=1)
            obs[:, COST_TO_GO_CHANNEL] = cost_to_go_channel(
                cost_to_go_steps(distances, self.radius), self.radius)
        return obs.reshape(m, self.channels, self.size, self.size)


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
TIMING_EVERY = 50  # log the hub's per-tick time split every this many decisions


class TickTiming:
    """Where a hub's tick goes (plain Python), for the log and benchmarks/bench_fleet.py:
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


class HubExchange:
    """The per-tick exchange of the robots hosted in one process, without ROS: their FOV
    observations, the network's batched pieces (the numbers of the batched evaluator: same
    padding and masks), the peer messages through `link`, and the robots' ranked actions.
    The process's `PolicyHub` is its ROS `link`; tests link several exchanges in memory
    (test/ros/test_hub_exchange.py). `link` has:
      publish_hidden(episode, tick, round, ids, vectors)   DHC: this process's vectors of a round
      publish_announce(episode, tick, ids, targets)        DCC: whom its robots request
      send(kind, episode, tick, entries) -> (sent, calls)  DCC requests / replies to robots of
                                                           other processes: (sender, receiver,
                                                           vector) entries
      warn(text)
    and delivers what comes from the others to `receive_hidden`, `receive_announce`,
    `receive`."""

    def __init__(self, model, ids, comm_timeout: float, preference_mode: str, link):
        self.model = model.eval()
        self.algo = model.config.algo
        self.radius = int(model.config.obs_radius)
        self.ids = np.array(ids, dtype=np.int64)
        self.index_of = {int(r): m for m, r in enumerate(ids)}
        self.comm_timeout = float(comm_timeout)
        self.preference_mode = preference_mode
        self.link = link
        self.mailbox = Mailbox()
        self._observer: LocalObserver | None = None
        self._hidden: torch.Tensor | None = None  # (M, H) carried post-communication hidden
        self._episode = None
        self._tick = -1
        self.decisions = 0
        self.sent = {"local": 0, "service": 0, "batches": 0, "unsent": 0}
        self.timing = TickTiming()

    @property
    def episode(self):
        return self._episode

    @property
    def tick(self) -> int:
        return self._tick

    # ---- what the other processes send ----
    def receive_hidden(self, episode: int, tick: int, round_index: int, ids, vectors) -> None:
        if len(ids) and int(ids[0]) in self.index_of:
            return  # our own message: delivered locally already
        self.mailbox.put_many(episode, f"dhc{round_index}", tick, zip(ids, vectors))

    def receive_announce(self, episode: int, tick: int, ids, targets) -> None:
        if len(ids) and int(ids[0]) in self.index_of:
            return
        self.mailbox.put_many(episode, "announce", tick, zip(ids, targets))

    def receive(self, kind: str, episode: int, tick: int, senders, receivers, vectors) -> int:
        """DCC requests or replies for robots of this process; how many were stored."""
        return sum(self.mailbox.put(episode, f"{kind}{int(r)}", tick, int(s), vectors[k])
                   for k, (s, r) in enumerate(zip(senders, receivers))
                   if int(r) in self.index_of)

    # ---- one tick ----
    def enter(self, episode: int, tick: int) -> None:
        """The fleet is at `tick` of `episode`: older messages go; a new run, or a tick
        skipped (joined mid-run, restarted), starts the robots with a fresh recurrent state."""
        if episode != self._episode or tick != self._tick + 1:
            self._hidden = None
        self._episode, self._tick = episode, int(tick)
        self.mailbox.set_tick(episode, int(tick))

    def decide(self, grid, positions, goals, last_actions=None, started=None,
               arrived=(None, None), stamp=None):
        """The local robots' decisions of the tick entered: (preferences (M, 5), requested,
        received, missing) per robot, or None when the fleet moved on meanwhile (stale)."""
        tick = self._tick
        started = time.perf_counter() if started is None else started
        positions = np.asarray(positions, dtype=np.int64)
        goals = np.asarray(goals, dtype=np.int64)
        if int(self.ids.max()) >= len(positions):
            raise ValueError(f"robot ids {self.ids.tolist()} do not fit a fleet of "
                             f"{len(positions)} robots")
        local_goals = goals[self.ids]
        key = (grid.shape, grid.tobytes(), local_goals.tobytes())
        if self._observer is None or self._observer.key != key:
            self._observer = LocalObserver(grid, local_goals, self.radius,
                                           self.model.config.observation)
        obs = torch.from_numpy(self._observer.observe(positions, self.ids))
        self.timing.begin(started, arrived, stamp)
        self.timing.mark("observe")
        if self._hidden is None:
            self._hidden = torch.zeros(len(self.ids), self.model.config.hidden_dim)
        with torch.no_grad():
            if self.algo == "dhc":
                h, requested, received, missing = self._dhc(tick, obs, positions)
            else:
                last = torch.as_tensor(np.asarray(last_actions, dtype=np.int64)[self.ids])
                h, requested, received, missing = self._dcc(tick, obs, last, positions)
            q = self.model.head(h).numpy()
        self.timing.mark("network")
        preferences = rank_actions(obs.numpy(), q, self.preference_mode,
                                   ties=tie_breakers(self.ids, tick))
        if self.mailbox.current_tick != tick:
            return None  # the fleet moved on while we waited: this decision is stale
        self._hidden = h
        self.decisions += 1
        return preferences, requested, received, missing

    def _deadline(self) -> float:
        return time.monotonic() + self.comm_timeout

    # ---- DHC: two rounds over the shared topic ----
    def _dhc(self, tick, obs, positions):
        from mapf_fleet.models.comm import dhc_partners

        model, m_count = self.model, len(self.ids)
        h = model.encode_batch(obs, self._hidden)
        self.timing.mark("network")
        partners = dhc_partners(positions, self.radius, model.config.max_partners)[self.ids]
        wanted = {int(j) for j in partners.reshape(-1) if j >= 0}
        missing = [set() for _ in range(m_count)]
        received = [0] * m_count
        for r in range(model.config.comm_rounds):
            vectors = h.numpy().copy()
            self.mailbox.put_many(self._episode, f"dhc{r}", tick, zip(self.ids.tolist(), vectors))
            self.link.publish_hidden(self._episode, tick, r, self.ids, vectors)
            self.timing.mark("send")
            box = self.mailbox.wait_for(f"dhc{r}", tick, wanted, self._deadline())
            self.timing.mark("wait")
            # members: self first, then the partners nearest first (as the batched step)
            members = np.zeros((m_count, 1 + partners.shape[1], h.shape[1]), dtype=np.float32)
            valid = np.zeros(members.shape[:2], dtype=bool)
            members[:, 0], valid[:, 0] = vectors, True
            for m in range(m_count):
                for k, j in enumerate(partners[m]):
                    if j < 0:
                        continue
                    if int(j) in box:
                        members[m, 1 + k], valid[m, 1 + k] = box[int(j)], True
                        received[m] += 1
                    else:
                        missing[m].add(int(j))
            rows = torch.from_numpy(np.flatnonzero(valid[:, 1:].any(1)))
            if rows.numel():
                updated = model.round_batch(h[rows], torch.from_numpy(members)[rows],
                                       torch.from_numpy(valid)[rows])
                h = h.index_put((rows,), updated)
            self.timing.mark("network")
        requested = [[int(j) for j in row if j >= 0] for row in partners]
        return h, requested, received, missing

    # ---- DCC: announcements over a topic, requests and replies as services ----
    def _dcc(self, tick, obs, last, positions):
        model, m_count = self.model, len(self.ids)
        delta = positions[None, :, :] - positions[self.ids][:, None, :]  # (M, N, 2)
        inside = (np.abs(delta) <= self.radius).all(-1)
        inside[np.arange(m_count), self.ids] = False
        owner, neighbour = np.nonzero(inside)  # index order per robot, as the batched step
        h, variant_actions = model.encode_with_variants(
            obs, last, self._hidden, torch.from_numpy(owner),
            torch.from_numpy(delta[owner, neighbour]))
        own_actions = model.greedy_actions(h).numpy()
        chosen = variant_actions.numpy() != own_actions[owner]
        targets = [[] for _ in range(m_count)]
        for m, j in zip(owner[chosen], neighbour[chosen]):
            targets[m].append(int(j))
        missing = [set() for _ in range(m_count)]
        received = [0] * m_count
        vectors = h.numpy().copy()
        self.timing.mark("network")
        self.mailbox.put_many(self._episode, "announce", tick, zip(self.ids.tolist(), targets))
        self.link.publish_announce(self._episode, tick, self.ids, targets)
        self._dispatch("request", tick, [(int(r), j, vectors[m])
                                         for m, r in enumerate(self.ids) for j in targets[m]])
        self.timing.mark("send")
        # Requesters of a robot are among its FOV neighbours (the FOV is symmetric): their
        # announcements tell how many requests to await. One deadline per phase, whatever the
        # number of local robots.
        neighbours = [set(neighbour[owner == m].tolist()) for m in range(m_count)]
        deadline = self._deadline()
        announced = self.mailbox.wait_for("announce", tick, set().union(*neighbours), deadline)
        requests = []
        for m, robot in enumerate(self.ids.tolist()):
            missing[m].update(neighbours[m] - set(announced))
            requesters = [i for i, t in announced.items() if i in neighbours[m] and robot in t]
            got = self.mailbox.wait_for(f"request{robot}", tick, requesters, deadline)
            missing[m].update(set(requesters) - set(got))
            received[m] += len(got)
            requests.append(got)
        self.timing.mark("wait")
        h1 = self._aggregate(model.request_comm, h, requests, positions)
        vectors1 = h1.numpy().copy()
        self.timing.mark("network")
        self._dispatch("reply", tick, [(int(r), i, vectors1[m])
                                       for m, r in enumerate(self.ids) for i in requests[m]])
        self.timing.mark("send")
        replies = []
        deadline = self._deadline()
        for m, robot in enumerate(self.ids.tolist()):
            got = self.mailbox.wait_for(f"reply{robot}", tick, targets[m], deadline)
            missing[m].update(set(targets[m]) - set(got))
            received[m] += len(got)
            replies.append(got)
        self.timing.mark("wait")
        h2 = self._aggregate(model.reply_comm, h1, replies, positions)
        return h2, targets, received, missing

    def _aggregate(self, layer, h, messages, positions):
        """Run a DCC comm layer for the local robots that received messages (senders in index
        order, padded and masked as in the batched step); the others keep h."""
        from mapf_fleet.models.comm import relative_position_index

        rows = [m for m in range(len(self.ids)) if messages[m]]
        if not rows:
            return h
        width = max(len(messages[m]) for m in rows)
        sender_h = np.zeros((len(rows), width, h.shape[1]), dtype=np.float32)
        offsets = np.zeros((len(rows), width, 2), dtype=np.int64)
        valid = np.zeros((len(rows), width), dtype=bool)
        for k, m in enumerate(rows):
            for s, sender in enumerate(sorted(messages[m])):
                sender_h[k, s] = messages[m][sender]
                offsets[k, s] = positions[sender] - positions[self.ids[m]]
                valid[k, s] = True
        index = torch.as_tensor(rows)
        own = h[index]
        sender_t = torch.from_numpy(sender_h)
        position_index = relative_position_index(torch.from_numpy(offsets), self.radius)
        valid_t = torch.from_numpy(valid)
        if self.model.config.attend_self:
            sender_t, position_index, valid_t = self.model.with_self(own, sender_t,
                                                                      position_index, valid_t)
        return h.index_put((index,), layer(own, sender_t, position_index, valid_t))

    def _dispatch(self, kind: str, tick: int, messages) -> None:
        """DCC messages (sender, receiver, vector) of this tick from local robots: to a local
        receiver straight into the mailbox, the others through `link.send` (one call per
        receiving process; fire and forget: the receiver only stores them, so nobody blocks
        inside a callback and the protocol cannot deadlock; `comm_timeout` bounds every
        wait)."""
        remote = []
        for sender, receiver, vector in messages:
            if int(receiver) in self.index_of:
                self.mailbox.put(self._episode, f"{kind}{int(receiver)}", tick, sender, vector)
                self.sent["local"] += 1
            else:
                remote.append((int(sender), int(receiver), vector))
        if remote:
            sent, calls = self.link.send(kind, self._episode, tick, remote)
            self.sent["service"] += sent
            self.sent["unsent"] += len(remote) - sent
            self.sent["batches"] += calls


class PolicyHub:
    """The ROS side of one process's robots: subscriptions, heartbeats, the batch service and
    its clients, the decision thread; the numbers are its `HubExchange`'s."""

    def __init__(self, nodes, model):
        from mapf_fleet_interfaces.msg import (DccAnnounce, DhcHidden, FleetState,
                                               RobotStatus)
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
        self.exchange = HubExchange(model, ids, first.comm_timeout, first.preference_mode, self)
        self.algo = self.exchange.algo
        self.ids = self.exchange.ids
        self.index_of = self.exchange.index_of
        self._ids_array = array.array("I", ids)  # for the batched peer messages
        self.service_timeout = first.service_timeout
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
        self.node.create_subscription(FleetState, common.rel(common.STATE_TOPIC), self._on_state,
                                      common.reliable_qos(10), callback_group=group)
        self.node.create_subscription(RobotStatus, common.rel(common.STATUS_TOPIC),
                                      self._on_status,
                                      common.reliable_qos(1000), callback_group=group)
        quiet = common.quiet_publisher_events()
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
            self._latest_state = msg  # a slow or restarted hub skips to the newest tick
            self._state_at = (time.perf_counter(), time.time())
            back = self.watch.note(msg.tick, msg.done)
            self._state_cond.notify_all()
        if back:
            self.node.get_logger().info(back)

    def _on_status(self, msg):
        host = msg.host
        self._hosts[int(msg.robot_id)] = host
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
        """Every `status_period`: the hosted robots' heartbeats, when it is their turn. Up to
        HEARTBEAT_ROBOTS robots heard, every period; in a larger fleet every
        (robots heard / HEARTBEAT_ROBOTS) periods, so the whole fleet sends about
        HEARTBEAT_ROBOTS heartbeats per period whatever its size (every hub and the simulator
        take every heartbeat: 256 robots at 2 Hz were 4,600 callbacks a second, enough to delay
        the fleet state by seconds). A change of readiness or episode goes out at once."""
        from mapf_fleet_interfaces.msg import RobotStatus

        self._beats += 1
        every = max(1, len(self._hosts) // HEARTBEAT_ROBOTS)
        ready, episode = self.grid is not None, self.binding.reported
        if (ready, episode) == self._last_beat and self._beats % every:
            return
        self._last_beat = (ready, episode)
        peers = self.peers_reachable()
        for node in self.nodes:
            node.status_pub.publish(RobotStatus(
                episode=episode, robot_id=node.robot_id, tick=max(self.exchange.tick, 0),
                ready=ready, peers=peers, host=self.host,
                detail=f"{self.algo}, {len(self.nodes)} robots on this host, "
                       f"{self.exchange.decisions} decisions, "
                       f"{self.exchange.mailbox.stale_dropped} stale "
                       f"messages ignored"))

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
        preferences, requested, received, missing = decision
        from mapf_fleet_interfaces.msg import RobotMove

        tick = exchange.tick
        for m, node in enumerate(self.nodes):
            ranking = preferences[m].tolist()
            node.move_pub.publish(RobotMove(
                episode=state.episode, tick=tick, robot_id=node.robot_id, action=ranking[0],
                preferences=ranking, missing_peers=sorted(missing[m]), requested=requested[m],
                messages_received=received[m]))
        exchange.timing.mark("moves")
        exchange.timing.end()
        if any(missing):
            left_out = {int(self.ids[m]): sorted(s) for m, s in enumerate(missing) if s}
            self.warn(f"tick {tick}: left out peers {left_out}")
        if exchange.decisions % TIMING_EVERY == 0:
            self.node.get_logger().info(exchange.timing.text(exchange.sent))

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
