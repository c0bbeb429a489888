"""What one robot computes each tick, as plain Python (no rclpy): its FOV observation from the
map and the shared fleet state, then the per-robot inference steps of its network. The policy
node only moves these values over ROS; `run_in_process` moves them by direct calls, which is the
reference the fleet is tested against.

Per tick:
- DHC: `begin_tick` -> `dhc_partners()`; for round r in 0..rounds-1: send `message`, receive the
  partners' messages of round r, `dhc_round(r, received)`; then `decide()`.
- DCC: `begin_tick` -> `dcc_targets()` (whom it requests: its decision-causal neighbours);
  requests carry `message`; the receiver `dcc_absorb_requests(received)`, replies with `message`;
  the requester `dcc_absorb_replies(received)`; then `decide()`.
Received messages are dicts sender id -> hidden vector; the sender's position comes from the
shared fleet state. Senders left out (timeouts) are simply absent from the dict.
"""

from __future__ import annotations

import numpy as np
import torch

from mapf_fleet.grid.env import observe
from mapf_fleet.grid.heuristic import heuristic_channels


class RobotBrain:
    def __init__(self, model, robot_id: int, radius: int = 4):
        self.model = model
        self.robot_id = int(robot_id)
        self.radius = int(radius)
        self.algo = model.config.algo
        self._channels_key = None
        self._channels = None
        self.hidden = None  # carried between ticks (post-communication hidden)
        self.message = None  # current vector: what this robot sends in the current phase
        self.positions = None
        self.obs = None
        self.last_action = -1

    def reset(self) -> None:
        """Forget the recurrent state (a new episode, or a restarted node)."""
        self.hidden = None
        self.message = None

    # ---- observation ----
    def _own_channels(self, grid: np.ndarray, goal) -> np.ndarray:
        key = (grid.shape, grid.tobytes(), tuple(int(v) for v in goal))
        if key != self._channels_key:
            self._channels = heuristic_channels(grid, tuple(int(v) for v in goal))
            self._channels_key = key
        return self._channels

    def begin_tick(self, grid, positions, goals, last_actions=None) -> None:
        """Observe the fleet state of this tick and run the encoder."""
        grid = np.asarray(grid)
        positions = np.asarray(positions, dtype=np.int64)
        goals = np.asarray(goals, dtype=np.int64)
        n = positions.shape[0]
        if not 0 <= self.robot_id < n:
            raise ValueError(f"robot_id {self.robot_id} not in a fleet of {n} robots")
        own = self._own_channels(grid, goals[self.robot_id])
        # obs[i] reads only channels[i]: broadcasting our own channels avoids computing the
        # other robots' heuristics, which this robot does not need.
        channels = np.broadcast_to(own, (n,) + own.shape)
        self.obs = observe(grid, positions, goals, channels, self.radius)[self.robot_id]
        self.positions = positions
        with torch.no_grad():
            if self.algo == "dhc":
                self.message = self.model.encode(self.obs, self.hidden)
            else:
                self.last_action = -1 if last_actions is None else int(last_actions[self.robot_id])
                self.message = self.model.encode(self.obs, self.last_action, self.hidden)

    def offset_of(self, sender: int) -> np.ndarray:
        """Sender's cell minus this robot's cell."""
        return self.positions[int(sender)] - self.positions[self.robot_id]

    def fov_neighbours(self) -> list[int]:
        from mapf_fleet.models.comm import fov_neighbours

        indices, _ = fov_neighbours(self.positions, self.robot_id, self.radius)
        return [int(i) for i in indices]

    # ---- DHC ----
    def dhc_partners(self) -> list[int]:
        from mapf_fleet.models.comm import dhc_partners

        row = dhc_partners(self.positions, self.radius,
                           self.model.config.max_partners)[self.robot_id]
        return [int(j) for j in row if j >= 0]

    def dhc_round(self, round_index: int, received: dict) -> None:
        """Attend over the partners' vectors of this round that arrived (nearest first)."""
        vectors = [torch.as_tensor(np.asarray(received[j], dtype=np.float32))
                   for j in self.dhc_partners() if j in received]
        with torch.no_grad():
            self.message = self.model.comm_round(round_index, self.message, vectors)

    # ---- DCC ----
    def dcc_targets(self) -> list[int]:
        """The neighbours whose erasure changes this robot's greedy action (it requests them)."""
        indices, offsets = self._neighbours_with_offsets()
        if len(indices) == 0:
            return []
        with torch.no_grad():
            chosen = self.model.causal_set(self.obs, self.last_action, self.hidden, offsets)
        return [int(j) for j, keep in zip(indices, np.asarray(chosen, dtype=bool)) if keep]

    def _neighbours_with_offsets(self):
        from mapf_fleet.models.comm import fov_neighbours

        return fov_neighbours(self.positions, self.robot_id, self.radius)

    def _senders(self, received: dict):
        senders = sorted(int(s) for s in received)
        return senders, [(self.offset_of(s), torch.as_tensor(np.asarray(received[s], dtype=np.float32)))
                         for s in senders]

    def dcc_absorb_requests(self, received: dict) -> None:
        """Update with the requests that arrived; afterwards `message` is the reply."""
        senders, messages = self._senders(received)
        if not senders:  # no request: the batched step leaves non-receivers unchanged
            return
        with torch.no_grad():
            self.message = self.model.aggregate_requests(self.message, messages)

    def dcc_absorb_replies(self, received: dict) -> None:
        senders, messages = self._senders(received)
        if not senders:
            return
        with torch.no_grad():
            self.message = self.model.aggregate_replies(self.message, messages)

    # ---- decision ----
    def decide(self) -> int:
        with torch.no_grad():
            q = self.model.q_values(self.message)
        self.hidden = self.message
        return int(torch.argmax(q).item())


def run_tick_in_process(brains: list[RobotBrain], grid, positions, goals, last_actions=None,
                        drop=None) -> np.ndarray:
    """One tick of a whole fleet with direct message passing (lossless unless `drop(kind,
    sender, receiver)` says so): the reference a ROS fleet must reproduce."""
    drop = drop or (lambda kind, sender, receiver: False)
    for brain in brains:
        brain.begin_tick(grid, positions, goals, last_actions)
    algo = brains[0].algo
    if algo == "dhc":
        rounds = brains[0].model.config.comm_rounds
        for r in range(rounds):
            sent = {b.robot_id: b.message for b in brains}
            for b in brains:
                b.dhc_round(r, {j: sent[j] for j in b.dhc_partners()
                                if not drop("dhc", j, b.robot_id)})
    else:
        targets = {b.robot_id: b.dcc_targets() for b in brains}
        sent = {b.robot_id: b.message for b in brains}
        for b in brains:
            b.dcc_absorb_requests({i: sent[i] for i, t in targets.items()
                                   if b.robot_id in t and not drop("request", i, b.robot_id)})
        replies = {b.robot_id: b.message for b in brains}
        for b in brains:
            b.dcc_absorb_replies({j: replies[j] for j in targets[b.robot_id]
                                  if not drop("reply", j, b.robot_id)})
    return np.array([b.decide() for b in brains], dtype=np.int64)
