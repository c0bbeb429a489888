"""Prioritized sequence replay (Ape-X / R2D2 style) over fixed-shape sequence slots.

A replay item is one sequence of `seq_len` trained steps of one episode, stored with every agent
(padded to `max_agents`), `burn_in` steps before it, `n_step` steps after it for the bootstrap, the
hidden state the actor had at the window's first step, and the n-step reward sums already
computed (rewards are fixed at the actor, Eq. 2 included). Observations are bit-packed: the six
9x9 channels are binary, so 486 bits = 61 bytes per agent-step instead of 1944 as float32.

Sampling is proportional to priority^alpha with a sum tree; importance weights
w_i = (N * P(i))^-beta are normalised by the batch maximum (Ape-X).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapf_fleet.grid.observation import COST_TO_GO_CHANNEL, cost_to_go_channel, steps_from_cost_to_go

OBS_SHAPE = (6, 9, 9)
OBS_RADIUS = (OBS_SHAPE[-1] - 1) // 2
OBS_BITS = int(np.prod(OBS_SHAPE))
OBS_BYTES = (OBS_BITS + 7) // 8
FAR_AWAY = -10_000  # position of padding agents: never inside anyone's FOV


def pack_obs(obs: np.ndarray) -> np.ndarray:
    """(..., 6, 9, 9) binary -> (..., 61) uint8. Of a "cost_to_go" observation (..., 7, 9, 9)
    the six binary channels; its cost-to-go channel is not binary: `pack_cost_to_go`."""
    obs = np.asarray(obs)[..., :OBS_SHAPE[0], :, :]
    flat = obs.reshape(*obs.shape[:-3], OBS_BITS) > 0.5
    return np.packbits(flat, axis=-1)


def pack_cost_to_go(obs: np.ndarray) -> np.ndarray:
    """int8 (..., 9, 9): the cost-to-go channel of "cost_to_go" observations (..., 7, 9, 9) as
    whole steps (`grid.env.steps_from_cost_to_go`, exact)."""
    return steps_from_cost_to_go(np.asarray(obs)[..., COST_TO_GO_CHANNEL, :, :], OBS_RADIUS)


def unpack_obs(bits: np.ndarray, cost_to_go: np.ndarray | None = None) -> np.ndarray:
    """(..., 61) uint8 -> (..., 6, 9, 9) float32; with `cost_to_go` (..., 9, 9) int8 from
    `pack_cost_to_go`, the "cost_to_go" observation (..., 7, 9, 9)."""
    flat = np.unpackbits(bits, axis=-1, count=OBS_BITS)
    obs = flat.reshape(*bits.shape[:-1], *OBS_SHAPE).astype(np.float32)
    if cost_to_go is None:
        return obs
    channel = cost_to_go_channel(cost_to_go, OBS_RADIUS)[..., None, :, :]
    return np.concatenate([obs, channel], axis=-3)


class SumTree:
    """Binary sum tree over `capacity` leaves; batch updates and stratified batch sampling."""

    def __init__(self, capacity: int):
        if capacity < 1:
            raise ValueError(f"SumTree capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self.leaf_base = 1 << int(np.ceil(np.log2(max(capacity, 1))))
        self.nodes = np.zeros(2 * self.leaf_base, dtype=np.float64)

    @property
    def total(self) -> float:
        return float(self.nodes[1])

    def get(self, index: np.ndarray) -> np.ndarray:
        return self.nodes[self.leaf_base + np.asarray(index)]

    def update(self, index: np.ndarray, value: np.ndarray) -> None:
        index = np.asarray(index, dtype=np.int64)
        value = np.asarray(value, dtype=np.float64)
        if np.any(value < 0) or not np.all(np.isfinite(value)):
            raise ValueError("SumTree priorities must be finite and >= 0")
        # Last write wins for duplicated indices, then parents are recomputed level by level so
        # duplicates cannot double-count.
        nodes = np.unique(index) + self.leaf_base
        self.nodes[index + self.leaf_base] = value
        while nodes[0] > 1:
            nodes = np.unique(nodes // 2)
            self.nodes[nodes] = self.nodes[2 * nodes] + self.nodes[2 * nodes + 1]

    def find(self, mass: np.ndarray) -> np.ndarray:
        """Leaf index whose cumulative-sum interval holds each mass value (vectorised descent)."""
        mass = np.asarray(mass, dtype=np.float64).copy()
        node = np.ones(mass.shape, dtype=np.int64)
        for _ in range(self.leaf_base.bit_length() - 1):  # tree depth; all leaves at one depth
            left = 2 * node
            left_sum = self.nodes[left]
            go_right = mass >= left_sum
            mass = np.where(go_right, mass - left_sum, mass)
            node = np.where(go_right, left + 1, left)
        leaf = node - self.leaf_base
        return np.minimum(leaf, self.capacity - 1)


@dataclass
class SequenceBatch:
    """A sampled batch; arrays have the leading batch dimension B, W = window_len, L = seq_len."""

    obs: np.ndarray  # (B, W, N, 6, 9, 9) float32
    positions: np.ndarray  # (B, W, N, 2) int64
    last_actions: np.ndarray  # (B, W, N) int64, action taken before each window step, -1 none
    actions: np.ndarray  # (B, L, N) int64, action taken at each trained step
    returns: np.ndarray  # (B, L, N) float32, discounted reward sums over up to n steps
    boot_discount: np.ndarray  # (B, L) float32, gamma^m, 0 when the episode terminated first
    boot_index: np.ndarray  # (B, L) int64, window index of the bootstrap observation
    step_mask: np.ndarray  # (B, L) bool, trained step exists in the episode
    agent_mask: np.ndarray  # (B, N) bool
    start_index: np.ndarray  # (B,) int64, window index where the stored hidden applies
    hidden: np.ndarray  # (B, N, H) float32, hidden state at window index start_index
    weights: np.ndarray  # (B,) float32 importance weights
    indices: np.ndarray  # (B,) slot indices, for update_priorities


class PrioritizedSequenceReplay:
    """Ring buffer of sequence slots with proportional prioritized sampling."""

    def __init__(self, capacity: int, window_len: int, seq_len: int, max_agents: int,
                 hidden_dim: int, alpha: float = 0.6, eps: float = 1e-6, seed: int = 0):
        self.capacity, self.window_len, self.seq_len = capacity, window_len, seq_len
        self.max_agents, self.hidden_dim = max_agents, hidden_dim
        self.alpha, self.eps = alpha, eps
        self.tree = SumTree(capacity)
        self.rng = np.random.default_rng(seed)
        c, w, l, n = capacity, window_len, seq_len, max_agents
        self.obs_bits = np.zeros((c, w, n, OBS_BYTES), np.uint8)
        self.positions = np.full((c, w, n, 2), FAR_AWAY, np.int16)
        self.last_actions = np.full((c, w, n), -1, np.int8)  # -1 = no action yet / padding
        self.actions = np.zeros((c, l, n), np.uint8)
        self.returns = np.zeros((c, l, n), np.float32)
        self.boot_discount = np.zeros((c, l), np.float32)
        self.boot_index = np.zeros((c, l), np.int16)
        self.step_mask = np.zeros((c, l), bool)
        self.agent_mask = np.zeros((c, n), bool)
        self.start_index = np.zeros(c, np.int16)
        self.hidden = np.zeros((c, n, hidden_dim), np.float16)
        self.next_slot = 0
        self.size = 0
        self.max_priority = 1.0
        self.added_steps = 0  # trained (env) steps ever added

    def __len__(self) -> int:
        return self.size

    def add(self, seq: dict) -> int:
        """Store one sequence (a dict from `episodes.episode_to_sequences`) at max priority."""
        slot = self.next_slot
        n = seq["actions"].shape[1]
        if n > self.max_agents:
            raise ValueError(f"sequence has {n} agents, replay holds at most {self.max_agents}")
        h = seq["hidden"].shape[-1]
        if h != self.hidden_dim:
            raise ValueError(f"sequence hidden size {h} != replay hidden size {self.hidden_dim}")
        self.obs_bits[slot] = 0
        self.obs_bits[slot, :, :n] = seq["obs_bits"]
        self.positions[slot] = FAR_AWAY
        self.positions[slot, :, :n] = seq["positions"]
        self.last_actions[slot] = -1
        self.last_actions[slot, :, :n] = seq["last_actions"]
        self.actions[slot] = 0
        self.actions[slot, :, :n] = seq["actions"]
        self.returns[slot] = 0
        self.returns[slot, :, :n] = seq["returns"]
        self.boot_discount[slot] = seq["boot_discount"]
        self.boot_index[slot] = seq["boot_index"]
        self.step_mask[slot] = seq["step_mask"]
        self.agent_mask[slot] = False
        self.agent_mask[slot, :n] = True
        self.start_index[slot] = seq["start_index"]
        self.hidden[slot] = 0
        self.hidden[slot, :n] = seq["hidden"]
        self.tree.update(np.array([slot]), np.array([self.max_priority ** self.alpha]))
        self.next_slot = (slot + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)
        self.added_steps += int(seq["step_mask"].sum())
        return slot

    # -- persistence (resume) -------------------------------------------------------------------
    _ARRAYS = ("obs_bits", "positions", "last_actions", "actions", "returns", "boot_discount",
               "boot_index", "step_mask", "agent_mask", "start_index", "hidden")
    _SHAPE = ("capacity", "window_len", "seq_len", "max_agents", "hidden_dim")

    def state_dict(self) -> dict[str, np.ndarray]:
        """The stored sequences (filled slots only), their priorities and the counters; the
        sampling rng is not kept. Plain numpy arrays, for `np.savez`."""
        filled = self.size
        state = {name: getattr(self, name)[:filled] for name in self._ARRAYS}
        state["priorities"] = self.tree.get(np.arange(filled))
        for name in self._SHAPE + ("next_slot", "size", "added_steps"):
            state[name] = np.asarray(getattr(self, name), dtype=np.int64)
        state["max_priority"] = np.asarray(self.max_priority, dtype=np.float64)
        return state

    def load_state_dict(self, state) -> None:
        """Restore `state_dict()` output into this (empty, same-shaped) replay; a ValueError
        names the field that does not match, and the replay is left unchanged."""
        for name in self._SHAPE:
            saved = int(state[name])
            if saved != getattr(self, name):
                raise ValueError(f"replay {name}: saved {saved}, this run uses {getattr(self, name)}")
        filled = int(state["size"])
        for name in self._ARRAYS:
            array = state[name]
            expected = (filled,) + getattr(self, name).shape[1:]
            if array.shape != expected:
                raise ValueError(f"replay {name}: saved shape {array.shape}, expected {expected}")
        for name in self._ARRAYS:
            getattr(self, name)[:filled] = state[name]
        self.tree = SumTree(self.capacity)
        if filled:
            self.tree.update(np.arange(filled), np.asarray(state["priorities"], np.float64))
        self.size, self.next_slot = filled, int(state["next_slot"])
        self.added_steps = int(state["added_steps"])
        self.max_priority = float(state["max_priority"])

    def probabilities(self, indices: np.ndarray) -> np.ndarray:
        return self.tree.get(indices) / self.tree.total

    def sample_indices(self, batch_size: int) -> np.ndarray:
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay")
        total = self.tree.total
        segment = total / batch_size
        mass = (np.arange(batch_size) + self.rng.random(batch_size)) * segment
        return self.tree.find(np.minimum(mass, np.nextafter(total, 0)))

    def importance_weights(self, indices: np.ndarray, beta: float) -> np.ndarray:
        probs = self.probabilities(indices)
        weights = (self.size * probs) ** (-beta)
        return (weights / weights.max()).astype(np.float32)

    def sample(self, batch_size: int, beta: float) -> SequenceBatch:
        idx = self.sample_indices(batch_size)
        return SequenceBatch(
            obs=unpack_obs(self.obs_bits[idx]),
            positions=self.positions[idx].astype(np.int64),
            last_actions=self.last_actions[idx].astype(np.int64),
            actions=self.actions[idx].astype(np.int64),
            returns=self.returns[idx],
            boot_discount=self.boot_discount[idx],
            boot_index=self.boot_index[idx].astype(np.int64),
            step_mask=self.step_mask[idx],
            agent_mask=self.agent_mask[idx],
            start_index=self.start_index[idx].astype(np.int64),
            hidden=self.hidden[idx].astype(np.float32),
            weights=self.importance_weights(idx, beta),
            indices=idx,
        )

    def update_priorities(self, indices: np.ndarray, priorities: np.ndarray) -> None:
        priorities = np.asarray(priorities, dtype=np.float64) + self.eps
        self.max_priority = max(self.max_priority, float(priorities.max()))
        self.tree.update(indices, priorities ** self.alpha)
