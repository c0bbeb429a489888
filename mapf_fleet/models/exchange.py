"""The per-tick exchange of robots that decide with a learned policy, without ROS: the fleet's
forward pass of DHC and DCC for the robots one process hosts, with the messages between robots
going through a `link` (the ROS hub in `mapf_fleet.ros.hub`; tests and the checks below link
exchanges in memory).

- `PolicyExchange`: the robots' FOV observations (`grid.goal_observer.GoalObserver`), the
  network's batched pieces with the numbers of the batched `model.step` (same padding and
  masks), the peer messages through the link and into the `Mailbox`, and the robots' ranked
  actions (`coordination.ranking.rank_actions`, ties by `tie_breakers(robot id, tick)`).
  DHC: `comm_rounds` rounds of hidden vectors to every process. DCC: whom each robot requests
  (its decision-causal set) announced to every process, then requests and replies addressed
  to the robots' processes.
- `mailbox.Mailbox`: the messages of lockstep ticks, thread-safe; stale ticks are dropped.
- `mailbox.TickTiming`: where a tick's time goes (the hub's log, benchmarks/bench_fleet.py).
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from typing import NamedTuple

import numpy as np
import torch

from mapf_fleet.coordination.ranking import rank_actions, tie_breakers
from mapf_fleet.grid.goal_observer import GoalObserver

from .comm import dhc_partners
from .mailbox import Mailbox, TickTiming



class Decision(NamedTuple):
    """The local robots' decisions of one tick, one row per robot (in the exchange's order)."""

    rankings: np.ndarray  # int (M, 5): each robot's actions ranked, first choice first
    requested: list  # per robot: whom it asked (DHC partners, DCC decision-causal set)
    received: list  # per robot: how many peer messages it used
    missing: list  # per robot: the set of peers whose message was left out (comm_timeout)
    q: np.ndarray  # float32 (M, 5): the Q-values the ranking came from


class PolicyExchange:
    """The per-tick exchange of the robots hosted in one process, without ROS: their FOV
    observations, the network's batched pieces (the numbers of the batched evaluator: same
    padding and masks), the peer messages through `link`, and the robots' ranked actions.
    The process's `ros.hub.PolicyHub` is its ROS `link`; tests link several exchanges in memory
    (test/test_models_exchange.py). `link` has:
      publish_hidden(episode, tick, round, ids, vectors)   DHC: this process's vectors of a round
      publish_announce(episode, tick, ids, targets)        DCC: whom its robots request
      send(kind, episode, tick, entries) -> (sent, calls)  DCC requests / replies to robots of
                                                           other processes: (sender, receiver,
                                                           vector) entries
      warn(text)
    and delivers what comes from the others to `receive_hidden`, `receive_announce`,
    `receive`."""

    def __init__(self, model, ids, comm_timeout: float, ranking: str, link, guidance=None):
        self.model = model.eval()
        # where the model runs (the `device` parameter: cpu, or cuda when there is one); the
        # exchange's numpy inputs go there and its outputs come back to numpy
        self.device = next(model.parameters()).device
        # the guidance graph the robots' heuristic channels read (a `GuidanceSource` value or
        # None), the fleet's one value: the simulator's rule reads the same distances
        from mapf_fleet.grid.guidance_made import GuidanceSource

        self.guidance = GuidanceSource.parse(guidance)
        # online guidance: the graph followed from the fleet's states (`follow`), per map
        self._follower = None
        self.algo = model.config.algo
        self.radius = int(model.config.obs_radius)
        self.ids = np.array(ids, dtype=np.int64)
        self.index_of = {int(r): m for m, r in enumerate(ids)}
        self.comm_timeout = float(comm_timeout)
        self.ranking = ranking
        self.link = link
        self.mailbox = Mailbox()
        self._observer: GoalObserver | None = None
        self._observer_key = None
        self._hidden: torch.Tensor | None = None  # (M, H) carried post-communication hidden
        self._episode = None
        self._tick = -1
        self.decisions = 0
        self.sent = {"local": 0, "service": 0, "batches": 0, "unsent": 0}
        self.timing = TickTiming()

    def _tensor(self, array) -> torch.Tensor:
        return torch.as_tensor(array, device=self.device)

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
    def follow(self, episode: int, tick: int, grid, positions) -> str:
        """Every fleet state, in order, as it arrives (online guidance: the graph follows the
        robots' moves, `grid.guidance_made.FlowFollower`); why the graph can no longer follow
        the fleet's ("" while it can, and for static guidance)."""
        if not self.guidance.online or grid is None:
            return ""
        follower = self._follower_for(grid)
        follower.follow(episode, tick, positions)
        return follower.broken

    def _follower_for(self, grid):
        """The online guidance's follower of map `grid` (a new one for a new map: before any
        state it gives the run's first graph)."""
        follower = self._follower
        if follower is None or follower.grid.shape != grid.shape \
                or not np.array_equal(follower.grid, grid != 0):
            from mapf_fleet.grid.guidance_made import FlowFollower

            follower = self._follower = FlowFollower(self.guidance, grid)
        return follower

    def enter(self, episode: int, tick: int) -> None:
        """The fleet is at `tick` of `episode`: older messages go; a new run, or a tick
        skipped (joined mid-run, restarted), starts the robots with a fresh recurrent state."""
        if episode != self._episode or tick != self._tick + 1:
            self._hidden = None
        self._episode, self._tick = episode, int(tick)
        self.mailbox.set_tick(episode, int(tick))

    def decide(self, grid, positions, goals, last_actions=None, started=None,
               arrived=(None, None), stamp=None) -> Decision | None:
        """The local robots' `Decision` of the tick entered, from the fleet's state (every
        robot's cell, goal and last executed action), or None when the fleet moved on meanwhile
        (stale)."""
        started = time.perf_counter() if started is None else started
        positions = self._fleet_array(positions, "positions")
        goals = self._fleet_array(goals, "goals")
        local_goals = goals[self.ids]
        observation = self.model.config.observation
        key = (grid.shape, grid.tobytes(), observation)
        graph = self._follower_for(grid).at(self._tick) if self.guidance.online else None
        if self._observer is None or self._observer_key != key or (
                self.guidance.online and self._observer.guidance is not graph):
            # goals: searched when new; online guidance: a new graph every period
            self._observer = GoalObserver(grid, self.radius, observation,
                                          guidance=graph if self.guidance.online
                                          else self.guidance.for_map(grid))
            self._observer_key = key
        obs = self._observer.observe(positions, local_goals, self.ids)
        self.timing.begin(started, arrived, stamp)
        self.timing.mark("observe")
        return self.decide_on(obs, positions, last_actions)

    def decide_on(self, obs, positions, last_actions=None) -> Decision | None:
        """`decide` given the local robots' observations (M, C, S, S) (in `ids` order) and
        every robot's cell (N, 2) and last action (N,) (None or -1: none)."""
        tick = self._tick
        positions = self._fleet_array(positions, "positions")
        obs = self._tensor(np.asarray(obs, dtype=np.float32))
        if self._hidden is None:
            self._hidden = torch.zeros(len(self.ids), self.model.config.hidden_dim,
                                       device=self.device)
        with torch.no_grad():
            if self.algo == "dhc":
                h, requested, received, missing = self._dhc(tick, obs, positions)
            else:
                last = np.full(len(positions), -1, dtype=np.int64) if last_actions is None \
                    else np.asarray(last_actions, dtype=np.int64)
                h, requested, received, missing = self._dcc(
                    tick, obs, self._tensor(last[self.ids]), positions)
            q = self.model.head(h).cpu().numpy()
        self.timing.mark("network")
        rankings = rank_actions(obs.cpu().numpy(), q, self.ranking,
                                   ties=tie_breakers(self.ids, tick))
        if self.mailbox.current_tick != tick:
            return None  # the fleet moved on while we waited: this decision is stale
        self._hidden = h
        self.decisions += 1
        return Decision(rankings, requested, received, missing, q)

    def _fleet_array(self, values, name: str) -> np.ndarray:
        values = np.asarray(values, dtype=np.int64)
        if int(self.ids.max()) >= len(values):
            raise ValueError(f"robot ids {self.ids.tolist()} do not fit a fleet of "
                             f"{len(values)} robots ({name})")
        return values

    def _deadline(self) -> float:
        return time.monotonic() + self.comm_timeout

    # ---- DHC: two rounds over the shared topic ----
    def _dhc(self, tick, obs, positions):
        model, m_count = self.model, len(self.ids)
        h = model.encode_batch(obs, self._hidden)
        self.timing.mark("network")
        partners = dhc_partners(positions, self.radius, model.config.max_partners)[self.ids]
        wanted = {int(j) for j in partners.reshape(-1) if j >= 0}
        missing = [set() for _ in range(m_count)]
        received = [0] * m_count
        for r in range(model.config.comm_rounds):
            vectors = h.cpu().numpy().copy()
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
            rows = self._tensor(np.flatnonzero(valid[:, 1:].any(1)))
            if rows.numel():
                updated = model.round_batch(h[rows], self._tensor(members)[rows],
                                       self._tensor(valid)[rows])
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
            obs, last, self._hidden, self._tensor(owner),
            self._tensor(delta[owner, neighbour]))
        own_actions = model.greedy_actions(h).cpu().numpy()
        chosen = variant_actions.cpu().numpy() != own_actions[owner]
        targets = [[] for _ in range(m_count)]
        for m, j in zip(owner[chosen], neighbour[chosen]):
            targets[m].append(int(j))
        missing = [set() for _ in range(m_count)]
        received = [0] * m_count
        vectors = h.cpu().numpy().copy()
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
        vectors1 = h1.cpu().numpy().copy()
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
        index = self._tensor(rows)
        updated = self.model.receive(layer, h[index], self._tensor(sender_h),
                                     self._tensor(offsets), self._tensor(valid))
        return h.index_put((index,), updated)

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


class LinkedExchanges:
    """Exchanges of groups of robots (one per "process") linked by direct calls: the fleet's
    exchange driven in one process, without ROS (the hub's deliveries without DDS), for the
    tests and benchmarks that compare it with `model.step`. Each exchange decides in its own
    thread, as each process would. `drop(kind, sender, receiver)` loses a DCC request or reply.
    """

    def __init__(self, model, groups, comm_timeout: float = 5.0, ranking: str = "q",
                 drop=None):
        self.drop = drop or (lambda kind, sender, receiver: False)
        self.exchanges = [PolicyExchange(model, group, comm_timeout, ranking,
                                         _MemoryLink(self, k))
                          for k, group in enumerate(groups)]
        self.owner = {int(r): ex for ex in self.exchanges for r in ex.ids}
        self.calls = 0  # DCC batch calls between the groups

    def tick(self, episode: int, tick: int, positions, last_actions=None, grid=None,
             goals=None, obs=None) -> Decision:
        """Every robot's decision at `tick`, rows in robot id order: from the state (`grid`,
        `goals`) or from every robot's observation `obs` (N, C, S, S)."""
        results, errors = {}, []

        def run(k, ex):
            try:
                ex.enter(episode, tick)
                if obs is None:
                    results[k] = ex.decide(grid, positions, goals, last_actions)
                else:
                    results[k] = ex.decide_on(np.asarray(obs)[ex.ids], positions, last_actions)
            except Exception as exc:  # raised below, in the caller's thread
                errors.append(exc)

        threads = [threading.Thread(target=run, args=(k, ex))
                   for k, ex in enumerate(self.exchanges)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        if errors:
            raise errors[0]
        n = len(self.owner)
        rows = {}
        for k, ex in enumerate(self.exchanges):
            for m, robot in enumerate(ex.ids.tolist()):
                rows[robot] = [results[k][field][m] for field in range(len(Decision._fields))]
        ordered = [rows[i] for i in range(n)]
        return Decision(np.array([r[0] for r in ordered]), [r[1] for r in ordered],
                        [r[2] for r in ordered], [r[3] for r in ordered],
                        np.array([r[4] for r in ordered]))


class _MemoryLink:
    """The link of exchange `index` of a `LinkedExchanges`: straight calls of the others."""

    def __init__(self, fleet: LinkedExchanges, index: int):
        self.fleet, self.index = fleet, index

    def _others(self):
        return [ex for k, ex in enumerate(self.fleet.exchanges) if k != self.index]

    def publish_hidden(self, episode, tick, round_index, ids, vectors):
        for ex in self._others():
            ex.receive_hidden(episode, tick, round_index, ids.tolist(), vectors.copy())

    def publish_announce(self, episode, tick, ids, targets):
        for ex in self._others():
            ex.receive_announce(episode, tick, ids.tolist(), [list(t) for t in targets])

    def send(self, kind, episode, tick, entries):
        by_owner = defaultdict(list)
        for sender, receiver, vector in entries:
            if not self.fleet.drop(kind, sender, receiver):
                by_owner[id(self.fleet.owner[receiver])].append((sender, receiver, vector))
        for batch in by_owner.values():
            self.fleet.owner[batch[0][1]].receive(kind, episode, tick, [e[0] for e in batch],
                                                  [e[1] for e in batch],
                                                  np.stack([e[2] for e in batch]))
            self.fleet.calls += 1
        return sum(len(b) for b in by_owner.values()), len(by_owner)

    def warn(self, text):
        pass
