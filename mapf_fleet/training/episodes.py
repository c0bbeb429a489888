"""Episodes recorded by an actor, n-step return components, and slicing into replay sequences.

n-step target of step t (T steps in the episode, observation index T is the final observation):
    m = min(n, T - t)
    G_t = sum_{k<m} gamma^k R_{t+k} + gamma^m * max_a Q_target(o_{t+m}, a)
and the bootstrap term is dropped when t + m == T and the episode terminated (every agent on its
goal); an episode cut by the step limit is bootstrapped from its final observation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .replay import FAR_AWAY, OBS_BYTES, pack_obs


@dataclass
class EpisodeRecord:
    # (T+1, N, 6, 9, 9) binary observations (index T = after the last step), or the same
    # already bit-packed as (T+1, N, 61) uint8 (what actors send, to keep messages small)
    obs: np.ndarray
    positions: np.ndarray  # (T+1, N, 2)
    actions: np.ndarray  # (T, N)
    rewards: np.ndarray  # (T, N) rewards as trained on (Eq. 2 already applied)
    hidden: np.ndarray  # (T+1, N, H) hidden state fed into step t
    terminal: bool  # the episode ended by success (no bootstrap past the end)
    individual_rewards: np.ndarray | None = None  # (T, N) env rewards before Eq. 2 (for checks)
    # (T, N) the actions the environment executed, when they differ from the trained `actions`:
    # an actor behind the PIBT shield that trains each agent's own first choice
    # (`replay_action: preferred`). None = `actions` were executed. The last-action input of
    # every step (DCC's) is always the executed action, as at test time.
    executed_actions: np.ndarray | None = None

    @property
    def length(self) -> int:
        return int(self.actions.shape[0])


def n_step_components(rewards: np.ndarray, terminal: bool, gamma: float, n: int):
    """For rewards (T, ...) return (returns (T, ...), boot_discount (T,), boot_offset (T,)):
    returns[t] = sum_{k<m} gamma^k r[t+k], boot_offset[t] = m = min(n, T - t),
    boot_discount[t] = gamma^m, or 0 when the episode terminated within those m steps."""
    rewards = np.asarray(rewards, dtype=np.float64)
    length = rewards.shape[0]
    if n < 1:
        raise ValueError(f"n-step must be >= 1, got {n}")
    t = np.arange(length)
    offset = np.minimum(n, length - t)
    returns = np.zeros_like(rewards)
    for k in range(n):
        valid = k < offset
        shifted = np.zeros_like(rewards)
        shifted[: length - k] = rewards[k:]
        returns += (gamma ** k) * shifted * valid.reshape(-1, *([1] * (rewards.ndim - 1)))
    discount = gamma ** offset.astype(np.float64)
    if terminal:
        discount = np.where(t + offset == length, 0.0, discount)
    return returns.astype(np.float32), discount.astype(np.float32), offset.astype(np.int64)


def episode_to_sequences(ep: EpisodeRecord, seq_len: int, burn_in: int, n_step: int,
                         gamma: float) -> list[dict]:
    """Cut an episode into sequences of `seq_len` trained steps (the last one may be partial),
    each with a window of burn_in + seq_len + n_step observations (padded where the episode has
    none), the stored hidden state where its real data begins, and n-step components."""
    length = ep.length
    num_agents = ep.actions.shape[1]
    window = burn_in + seq_len + n_step
    returns, discount, offset = n_step_components(ep.rewards, ep.terminal, gamma, n_step)
    packed = ep.obs.dtype == np.uint8 and ep.obs.shape[-1] == OBS_BYTES and ep.obs.ndim == 3
    obs_bits = ep.obs if packed else pack_obs(ep.obs)  # (T+1, N, 61)
    # last action fed at each step; -1 = none yet (the env's and DCC's convention)
    executed = ep.actions if ep.executed_actions is None else ep.executed_actions
    if np.shape(executed) != np.shape(ep.actions):
        raise ValueError(f"executed_actions: shape {np.shape(executed)} differs from actions "
                         f"{np.shape(ep.actions)}")
    last_actions = np.concatenate([np.full((1, num_agents), -1, np.int64), executed], axis=0)
    sequences = []
    for t0 in range(0, length, seq_len):
        origin = t0 - burn_in  # episode index of window index 0
        first = max(0, origin)
        last = min(length, origin + window - 1)  # last episode obs index inside the window
        w_first, w_last = first - origin, last - origin
        seq_obs = np.zeros((window, num_agents, obs_bits.shape[-1]), np.uint8)
        seq_pos = np.full((window, num_agents, 2), FAR_AWAY, np.int16)
        seq_last = np.full((window, num_agents), -1, np.int8)
        seq_obs[w_first:w_last + 1] = obs_bits[first:last + 1]
        seq_pos[w_first:w_last + 1] = ep.positions[first:last + 1]
        seq_last[w_first:w_last + 1] = last_actions[first:last + 1]
        steps = np.arange(t0, t0 + seq_len)
        valid = steps < length
        clipped = np.minimum(steps, length - 1)
        seq_actions = np.where(valid[:, None], ep.actions[clipped], 0).astype(np.uint8)
        seq_returns = np.where(valid[:, None], returns[clipped], 0).astype(np.float32)
        seq_discount = np.where(valid, discount[clipped], 0).astype(np.float32)
        boot_index = np.where(valid, clipped + offset[clipped] - origin, 0).astype(np.int16)
        sequences.append({
            "obs_bits": seq_obs, "positions": seq_pos, "last_actions": seq_last,
            "actions": seq_actions, "returns": seq_returns, "boot_discount": seq_discount,
            "boot_index": boot_index, "step_mask": valid, "start_index": w_first,
            "hidden": ep.hidden[first].astype(np.float16),
        })
    return sequences
