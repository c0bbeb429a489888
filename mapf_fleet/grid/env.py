"""The MAPF grid environment of DHC/DCC: conflict resolution, rewards, and the episode.

Everything per step is vectorised over agents. Observations come from `grid.observation`'s
`ObservationBuilder` (built once per reset; `EnvConfig.observation` says which channels).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .actions import ACTION_DELTAS, NUM_ACTIONS, STAY
from .heuristic import HeuristicCache, default_cache
from .instance import Instance
# the observations live in grid.observation; their names stay importable from here
from .observation import (  # noqa: F401
    COST_TO_GO_CHANNEL, NUM_OBS_CHANNELS, OBSERVATIONS, ObservationBuilder, check_positions,
    cost_to_go_channel, cost_to_go_steps, observation_channels, observe, pad_distances,
    steps_from_cost_to_go,
)

FINISH_REWARD_MODES = ("team", "per_agent")


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
    guidance: the guidance graph the heuristic channels read (`guidance_made.GuidanceSource`:
        "none", "highways", a guidance file or a cost model); "none": BFS steps, the paper's.
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
    guidance: str = "none"

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
        from .guidance_made import GuidanceSource

        GuidanceSource.parse(self.guidance)  # refused here, before any episode


def guidance_for(config: EnvConfig, grid):
    """The `Guidance` of `config.guidance` on `grid` (None for "none"), built once per map."""
    if config.guidance in ("none", ""):
        return None
    from .guidance_made import GuidanceSource

    key = (config.guidance, np.asarray(grid).shape, np.asarray(grid).tobytes())
    found = _GUIDANCE.get(key)
    if found is None:
        found = _GUIDANCE[key] = GuidanceSource.parse(config.guidance).for_map(grid)
        while len(_GUIDANCE) > 64:
            del _GUIDANCE[next(iter(_GUIDANCE))]
    return found


_GUIDANCE: dict = {}


# ----------------------------------------------------------------------------------------------
# conflict resolution

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
    positions = check_positions(positions, grid.shape)
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
        self.guidance = guidance_for(self.config, self.grid)
        self._obs = ObservationBuilder.for_goals(self.grid, self.goals, self.config.obs_radius,
                                                 self.config.observation, self._cache,
                                                 self.guidance)

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
