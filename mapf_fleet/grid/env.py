"""The MAPF grid environment: conflict resolution, rewards and observations of DHC/DCC.

Everything per step is vectorised over agents. The static part of every agent's observation
(obstacle bit + its four heuristic bits) is packed into one byte per cell and padded once per
reset; a step then gathers one byte per FOV cell for the static part and one for the agents, and
unpacks the bits into the (N, 6, 9, 9) float32 observation.

Observations (`OBSERVATIONS`, `EnvConfig.observation`, recorded in a model's config): "paper",
the six channels above, or "cost_to_go", the same plus a 7th channel, the agent's normalised
cost-to-go over its FOV (`cost_to_go_channel`), gathered from its padded BFS distance map.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .actions import ACTION_DELTAS, NUM_ACTIONS, STAY
from .heuristic import (UNREACHABLE, HeuristicCache, compact_distances, default_cache,
                        pack_heuristic_channels)
from .instance import Instance

FINISH_REWARD_MODES = ("team", "per_agent")
NUM_OBS_CHANNELS = 6  # the paper's observation
OBSERVATIONS = ("paper", "cost_to_go")
COST_TO_GO_CHANNEL = NUM_OBS_CHANNELS  # index of the cost-to-go channel, after the paper's six


def observation_channels(observation: str) -> int:
    """How many channels `observation` has (6 paper, 7 cost_to_go)."""
    if observation not in OBSERVATIONS:
        raise ValueError(f"observation must be one of {OBSERVATIONS}, got {observation!r}")
    return NUM_OBS_CHANNELS + (observation == "cost_to_go")


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Environment settings; the defaults are the DHC/DCC reference values.

    finish_reward:
      "team" (reference): when every agent stands on its goal after a step, every agent gets
        `reward_finish` for that step instead of its step reward, and the episode ends.
      "per_agent": an agent gets `reward_finish` instead of its step reward on the step it first
        reaches its goal in the episode (first arrival only, so leaving and re-entering the goal
        cannot farm the bonus); the episode still ends, with no extra bonus, when every agent
        stands on its goal at once.
    observation: "paper" (6 channels) or "cost_to_go" (a 7th: `cost_to_go_channel`); a model
        says which it reads (`ModelConfig.observation`).
    """

    obs_radius: int = 4
    max_steps: int = 256
    reward_move: float = -0.075
    reward_stay_off_goal: float = -0.075
    reward_stay_on_goal: float = 0.0
    reward_collision: float = -0.5
    reward_finish: float = 3.0
    finish_reward: str = "team"
    observation: str = "paper"  # one of OBSERVATIONS: the channels `reset` / `step` return

    def __post_init__(self):
        if not isinstance(self.obs_radius, (int, np.integer)) or self.obs_radius < 1:
            raise ValueError(f"EnvConfig.obs_radius must be an int >= 1, got {self.obs_radius!r}")
        if not isinstance(self.max_steps, (int, np.integer)) or self.max_steps < 1:
            raise ValueError(f"EnvConfig.max_steps must be an int >= 1, got {self.max_steps!r}")
        for name in ("reward_move", "reward_stay_off_goal", "reward_stay_on_goal",
                     "reward_collision", "reward_finish"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) \
                    or not np.isfinite(value):
                raise ValueError(f"EnvConfig.{name} must be a finite number, got {value!r}")
        if self.finish_reward not in FINISH_REWARD_MODES:
            raise ValueError(f"EnvConfig.finish_reward must be one of {FINISH_REWARD_MODES}, "
                             f"got {self.finish_reward!r}")
        if self.observation not in OBSERVATIONS:
            raise ValueError(f"EnvConfig.observation must be one of {OBSERVATIONS}, "
                             f"got {self.observation!r}")


# ----------------------------------------------------------------------------------------------
# conflict resolution

def _check_positions(positions, shape) -> np.ndarray:
    positions = np.asarray(positions)
    if positions.ndim != 2 or positions.shape[1] != 2:
        raise ValueError(f"positions must have shape (N, 2), got {positions.shape}")
    positions = positions.astype(np.int64, copy=False)
    h, w = shape
    outside = (positions[:, 0] < 0) | (positions[:, 0] >= h) | (positions[:, 1] < 0) \
        | (positions[:, 1] >= w)
    if outside.any():
        i = int(np.flatnonzero(outside)[0])
        raise ValueError(f"agent {i} position {tuple(positions[i].tolist())} is outside the "
                         f"{h}x{w} map")
    return positions


def _check_actions(actions, num_agents: int) -> np.ndarray:
    actions = np.asarray(actions)
    if actions.shape != (num_agents,):
        raise ValueError(f"actions must have shape ({num_agents},), got {actions.shape}")
    if not np.issubdtype(actions.dtype, np.integer):
        raise ValueError(f"actions must be integers 0..{NUM_ACTIONS - 1}, got dtype {actions.dtype}")
    bad = (actions < 0) | (actions >= NUM_ACTIONS)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"agent {i} action {int(actions[i])} is not in 0..{NUM_ACTIONS - 1}")
    return actions.astype(np.int64, copy=False)


def _resolve_flat(blocked_flat, h, w, positions, actions, map_offset=None):
    """Core of `resolve_moves` on validated input; returns (new flat cells, collided).

    With `map_offset` (int (N,), a multiple of h*w per agent) the agents live on several maps of
    the same size stacked in `blocked_flat`; flat cells then include the offset, so conflicts
    never cross maps. Agent order (lowest index wins) is the order of the arrays.
    """
    n = positions.shape[0]
    index = np.arange(n)
    current = positions[:, 0] * w + positions[:, 1]
    target = positions + ACTION_DELTAS[actions]
    moving = actions != STAY
    # 1. off the map or into an obstacle: revert
    off_map = (target[:, 0] < 0) | (target[:, 0] >= h) | (target[:, 1] < 0) | (target[:, 1] >= w)
    target_flat = np.where(off_map, current, target[:, 0] * w + target[:, 1])
    if map_offset is not None:
        current = current + map_offset
        target_flat = target_flat + map_offset
    collided = moving & (off_map | blocked_flat[target_flat])
    moving &= ~collided
    nxt = np.where(moving, target_flat, current)
    cell_count = blocked_flat.shape[0]
    # 2. swaps: i moves onto j's cell while j moves onto i's cell -> both revert. Reverting never
    #    creates a swap, so one pass suffices.
    occupant = np.full(cell_count, -1, dtype=np.int64)
    occupant[current] = index
    other = occupant[nxt]
    safe_other = np.where(other >= 0, other, index)
    swapped = moving & (other >= 0) & (other != index) & moving[safe_other] \
        & (nxt[safe_other] == current)
    if swapped.any():
        collided |= swapped
        moving &= ~swapped
        nxt[swapped] = current[swapped]
    # 3. vertex conflicts, repeated until stable because every revert may block another mover:
    #    a cell claimed by a non-mover (stayer or reverted agent, which includes the occupant of
    #    the cell when it does not leave) keeps it and all movers into it revert; a cell claimed
    #    only by movers goes to the lowest index, the others revert.
    while True:
        counts = np.bincount(nxt, minlength=cell_count)
        contested = moving & (counts[nxt] > 1)
        if not contested.any():
            break
        held = np.zeros(cell_count, dtype=bool)
        held[nxt[~moving]] = True
        winner = np.full(cell_count, n, dtype=np.int64)
        np.minimum.at(winner, nxt[contested], index[contested])
        losers = contested & (held[nxt] | (winner[nxt] != index))
        collided |= losers
        moving &= ~losers
        nxt[losers] = current[losers]
    if map_offset is not None:
        nxt = nxt - map_offset
    return nxt, collided


def resolve_moves(grid, positions, actions) -> tuple[np.ndarray, np.ndarray]:
    """Apply one joint action with the DHC/DCC conflict rules.

    Rules, as in the reference environments: staying agents are fixed; a move off the map or into
    an obstacle is reverted; a swap reverts both agents; several movers into one free cell: the
    lowest index wins, the others revert; a mover into a cell whose occupant stays (or was
    reverted) reverts. Reverts cascade until nothing changes. Following into a vacated cell and
    rotations of three or more agents are allowed.

    Returns (new_positions int64 (N, 2), collided bool (N,)); collided[i] is True when agent i's
    move was reverted (each such revert is a collision).
    """
    grid = np.asarray(grid)
    if grid.ndim != 2:
        raise ValueError(f"grid must be 2-D, got shape {grid.shape}")
    positions = _check_positions(positions, grid.shape)
    actions = _check_actions(actions, positions.shape[0])
    h, w = grid.shape
    flat = positions[:, 0] * w + positions[:, 1]
    if np.bincount(flat, minlength=1).max(initial=0) > 1:
        raise ValueError("two agents share a cell in positions")
    nxt, collided = _resolve_flat((grid != 0).ravel(), h, w, positions, actions)
    return np.stack(np.divmod(nxt, w), axis=1), collided


# ----------------------------------------------------------------------------------------------
# rewards

def step_rewards(config: EnvConfig, actions, collided, was_on_goal, on_goal,
                 first_arrival=None):
    """Individual rewards of one step and whether every agent stands on its goal.

    move: reward_move; stay: reward_stay_on_goal if the agent stands on its goal else
    reward_stay_off_goal; a reverted move: reward_collision. Then the finish reward per
    `config.finish_reward` (see `EnvConfig`); `first_arrival` (bool, like `actions`) marks the
    agents that reached their goal for the first time this episode, used by "per_agent".
    Arrays are (N,) for one episode (returns float32 (N,), bool) or (B, N) for a batch
    (returns float32 (B, N), bool (B,)).
    """
    actions = np.asarray(actions)
    rewards = np.where(actions == STAY,
                       np.where(was_on_goal, config.reward_stay_on_goal, config.reward_stay_off_goal),
                       config.reward_move)
    rewards = np.where(collided, config.reward_collision, rewards).astype(np.float32)
    all_on_goal = np.all(on_goal, axis=-1)
    if config.finish_reward == "team":
        rewards[all_on_goal, ...] = config.reward_finish
    elif first_arrival is not None:
        rewards[first_arrival] = config.reward_finish
    return rewards, (bool(all_on_goal) if all_on_goal.ndim == 0 else all_on_goal)


# ----------------------------------------------------------------------------------------------
# observations

def cost_to_go_steps(window_distances, radius: int) -> np.ndarray:
    """int8 (..., S*S): each FOV cell's BFS distance to the agent's goal minus the distance at the
    agent's own cell (the middle of the window), clipped to +-(2r+1); obstacle, off-map and
    unreachable cells (`UNREACHABLE` in `window_distances` (..., S*S)), and every cell when the
    agent's own cell cannot reach its goal, hold 2r+1. `cost_to_go_channel` normalises them."""
    d = np.asarray(window_distances).astype(np.int32)
    bound = 2 * int(radius) + 1
    centre = d[..., d.shape[-1] // 2, None]
    blocked = (d == UNREACHABLE) | (centre == UNREACHABLE)
    return np.where(blocked, bound, np.clip(d - centre, -bound, bound)).astype(np.int8)


def cost_to_go_channel(steps, radius: int) -> np.ndarray:
    """float32 cost-to-go channel from `cost_to_go_steps`: steps / (2r+1), within [-1, 1].

    Relative to the agent's own cell, as SSIL's normalised cost-to-go (Veerapaneni et al.,
    ICRA 2025), so the values do not grow with the distance to the goal; 2r+1 bounds every cell
    whose difference the FOV's geometry allows (|steps| <= 2r) strictly inside (-1, 1), so the
    blocked value 1.0 (obstacles, off the map, unreachable) differs from every free cell except
    those 2r+1 or more steps farther from the goal than the agent (behind a wall), which clip
    to it. Every value is a multiple of 1/(2r+1): `steps_from_cost_to_go` inverts this exactly
    (int8 storage)."""
    return np.asarray(steps, dtype=np.float32) / np.float32(2 * int(radius) + 1)


def steps_from_cost_to_go(channel, radius: int) -> np.ndarray:
    """int8 steps of a cost-to-go channel (the inverse of `cost_to_go_channel`)."""
    return np.rint(np.asarray(channel, dtype=np.float32) * (2 * int(radius) + 1)).astype(np.int8)


def pad_distances(distances: np.ndarray, radius: int) -> np.ndarray:
    """(N, H+2r, W+2r) BFS distance maps (N, H, W) with `UNREACHABLE` off the map (its compact
    integer type: one map per agent)."""
    distances = compact_distances(distances)
    n, h, w = distances.shape
    r = int(radius)
    padded = np.full((n, h + 2 * r, w + 2 * r), UNREACHABLE, dtype=distances.dtype)
    padded[:, r:r + h, r:r + w] = distances
    return padded


class _ObservationBuilder:
    """Gathers all agents' FOV windows from maps padded once per instance.

    static byte per (agent, cell): bit 0 obstacle (off-map padded as obstacle), bits 1..4 the
    heuristic channels up/down/left/right (padded 0). Agents live in a padded occupancy map per
    map. `grids` is (B, H, W) and `map_of_agent` (N,) says on which map each agent is (B = 1 and
    all zeros for a single episode). With `distances` (N, H, W), each agent's BFS distances to
    its goal, observations get the cost-to-go channel (`cost_to_go_channel`).
    """

    def __init__(self, grids: np.ndarray, heuristic_bits: np.ndarray, radius: int,
                 map_of_agent: np.ndarray | None = None, distances: np.ndarray | None = None):
        if grids.ndim == 2:
            grids = grids[None]
        b, h, w = grids.shape
        n = heuristic_bits.shape[0]
        map_of_agent = np.zeros(n, np.int64) if map_of_agent is None else map_of_agent
        r = int(radius)
        self.radius = r
        self.size = 2 * r + 1
        hp, wp = h + 2 * r, w + 2 * r
        static = np.ones((n, hp, wp), dtype=np.uint8)  # off-map: obstacle bit only
        static[:, r:r + h, r:r + w] = (grids[map_of_agent] != 0).astype(np.uint8) \
            | (heuristic_bits << 1)
        self.static = static.reshape(-1)
        self.distances = None if distances is None else pad_distances(distances, r).reshape(-1)
        self.channels = NUM_OBS_CHANNELS + (distances is not None)
        self.occupancy = np.zeros(b * hp * wp, dtype=np.uint8)
        offsets = np.arange(self.size)
        # flat offsets of a window relative to its top-left corner in the padded map
        self.window = (offsets[:, None] * wp + offsets[None, :]).reshape(-1)
        self.agent_base = np.arange(n, dtype=np.int64) * (hp * wp)
        self.map_base = map_of_agent * (hp * wp)
        self.wp = wp
        # padded flat index of an agent's own cell relative to its window corner
        self.centre = r * wp + r

    def corners(self, positions: np.ndarray) -> np.ndarray:
        # window top-left in padded coordinates == agent cell in map coordinates
        return positions[:, 0] * self.wp + positions[:, 1]

    def set_agents(self, positions: np.ndarray) -> None:
        self.occupancy[:] = 0
        self.occupancy[self.map_base + self.corners(positions) + self.centre] = 1

    def move_agents(self, old_positions: np.ndarray, new_positions: np.ndarray) -> None:
        self.occupancy[self.map_base + self.corners(old_positions) + self.centre] = 0
        self.occupancy[self.map_base + self.corners(new_positions) + self.centre] = 1

    def build(self, positions: np.ndarray) -> np.ndarray:
        n = positions.shape[0]
        s = self.size
        corners = self.corners(positions)
        own_windows = (corners + self.agent_base)[:, None] + self.window  # (N, S*S)
        static = self.static[own_windows]
        obs = np.empty((n, self.channels, s * s), dtype=np.float32)
        obs[:, 0] = self.occupancy[(corners + self.map_base)[:, None] + self.window]
        obs[:, 0, (s * s) // 2] = 0.0  # the agent itself is not in its agent channel
        for bit in range(5):
            obs[:, 1 + bit] = (static >> bit) & 1
        if self.distances is not None:
            obs[:, COST_TO_GO_CHANNEL] = cost_to_go_channel(
                cost_to_go_steps(self.distances[own_windows], self.radius), self.radius)
        return obs.reshape(n, self.channels, s, s)


def observe(grid, positions, goals, channels, radius: int = 4, distances=None) -> np.ndarray:
    """float32 (N, 6, 2r+1, 2r+1) observations centred on each agent, (N, 7, ...) with
    `distances`.

    Channels: 0 other agents (self excluded), 1 obstacles (off-map cells count as obstacles),
    2..5 the agent's heuristic channels up/down/left/right (0 off the map). `channels` is the
    (N, 4, H, W) stack of the agents' heuristic channels; `goals` (N, 2) is only checked for
    shape, since the heuristic channels already encode the goals. `distances` (N, H, W), each
    agent's BFS distances to its goal (`HeuristicCache.distances`), adds channel 6, the
    "cost_to_go" observation's normalised cost-to-go (`cost_to_go_channel`).
    """
    grid = np.asarray(grid)
    positions = _check_positions(positions, grid.shape)
    n = positions.shape[0]
    if np.asarray(goals).shape != (n, 2):
        raise ValueError(f"goals must have shape ({n}, 2), got {np.asarray(goals).shape}")
    channels = np.asarray(channels)
    if channels.shape != (n, 4, *grid.shape):
        raise ValueError(f"channels must have shape ({n}, 4, {grid.shape[0]}, {grid.shape[1]}), "
                         f"got {channels.shape}")
    if distances is not None and np.asarray(distances).shape != (n, *grid.shape):
        raise ValueError(f"distances must have shape ({n}, {grid.shape[0]}, {grid.shape[1]}), "
                         f"got {np.asarray(distances).shape}")
    builder = _ObservationBuilder(grid, pack_heuristic_channels(channels), radius,
                                  distances=distances)
    builder.set_agents(positions)
    return builder.build(positions)


# ----------------------------------------------------------------------------------------------
# the environment

class MAPFEnv:
    """One MAPF episode on one instance.

    `reset(instance=None)` returns the first observation (optionally switching instance);
    `step(actions)` returns (obs, rewards float32 (N,), done, info) with info
    {"collisions": bool (N,), "on_goal": bool (N,), "success": bool, "steps": int}.
    Rewards are individual; apply `CooperativeReward` on top for Eq. 2.
    The episode ends on success or after `config.max_steps` steps; stepping a finished episode
    raises RuntimeError.

    Attributes: grid, positions (N, 2), goals (N, 2), num_agents, steps, last_actions (int (N,),
    -1 before the first step: the DCC reference feeds an all-zero one-hot then, see
    `last_action_one_hot`).
    """

    def __init__(self, instance: Instance, config: EnvConfig | None = None,
                 heuristic_cache: HeuristicCache | None = None):
        self.config = config if config is not None else EnvConfig()
        if not isinstance(self.config, EnvConfig):
            raise TypeError(f"config must be an EnvConfig, got {type(self.config).__name__}")
        self._cache = heuristic_cache if heuristic_cache is not None else default_cache
        self._load(instance)
        self.reset()

    def _load(self, instance: Instance) -> None:
        if not isinstance(instance, Instance):
            raise TypeError(f"instance must be an Instance, got {type(instance).__name__}")
        instance.validate()
        self.instance = instance
        self.grid = instance.grid
        self.goals = instance.goals
        self.num_agents = instance.num_agents
        h, w = self.grid.shape
        self._blocked_flat = (self.grid != 0).ravel()
        self._goal_flat = self.goals[:, 0] * w + self.goals[:, 1]
        distances = self._cache.distances(self.grid, self.goals) \
            if self.config.observation == "cost_to_go" else None
        bits = self._cache.bits(self.grid, self.goals)  # found by the distances' search
        self._obs = _ObservationBuilder(self.grid, bits, self.config.obs_radius,
                                        distances=distances)

    def reset(self, instance: Instance | None = None) -> np.ndarray:
        if instance is not None:
            self._load(instance)
        self.positions = self.instance.starts.copy()
        self.steps = 0
        self.done = False
        self.last_actions = np.full(self.num_agents, -1, dtype=np.int64)
        self._reached = self.on_goal()
        self._obs.set_agents(self.positions)
        return self._obs.build(self.positions)

    def on_goal(self) -> np.ndarray:
        w = self.grid.shape[1]
        return (self.positions[:, 0] * w + self.positions[:, 1]) == self._goal_flat

    def observe(self) -> np.ndarray:
        """The observation of the current state (the one the last reset/step returned)."""
        return self._obs.build(self.positions)

    def last_action_one_hot(self) -> np.ndarray:
        """float32 (N, 5) one-hot of `last_actions`; all zeros before the first step."""
        one_hot = np.zeros((self.num_agents, NUM_ACTIONS), dtype=np.float32)
        taken = self.last_actions >= 0
        one_hot[np.flatnonzero(taken), self.last_actions[taken]] = 1.0
        return one_hot

    def step(self, actions):
        if self.done:
            raise RuntimeError("the episode is over: call reset() before step()")
        actions = _check_actions(actions, self.num_agents)
        h, w = self.grid.shape
        was_on_goal = self.on_goal()
        nxt, collided = _resolve_flat(self._blocked_flat, h, w, self.positions, actions)
        new_positions = np.stack(np.divmod(nxt, w), axis=1)
        on_goal = nxt == self._goal_flat
        first_arrival = on_goal & ~self._reached
        self._reached |= on_goal
        rewards, success = step_rewards(self.config, actions, collided, was_on_goal, on_goal,
                                        first_arrival)
        self._obs.move_agents(self.positions, new_positions)
        self.positions = new_positions
        self.last_actions = actions.copy()
        self.steps += 1
        self.done = success or self.steps >= self.config.max_steps
        info = {"collisions": collided, "on_goal": on_goal, "success": success,
                "steps": self.steps}
        return self._obs.build(new_positions), rewards, self.done, info
