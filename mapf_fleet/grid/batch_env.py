"""B episodes stepped in lockstep, for evaluation and actors (one numpy call per step for all).

All instances of a batch share the map size and the number of agents (the test protocol runs
200 instances of one (size, agents) scenario). The batch is one set of arrays: the maps are
stacked, agent k of episode b is agent b*N + k of one big conflict resolution whose flat cells
carry a per-map offset, so conflicts never cross episodes and "lowest index wins" keeps each
episode's agent order. Results equal B independent `MAPFEnv`s (tested).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .actions import NUM_ACTIONS, STAY
from .env import EnvConfig, _resolve_flat, guidance_for, step_rewards
from .heuristic import HeuristicCache, default_cache
from .instance import Instance
from .observation import ObservationBuilder


class BatchMAPFEnv:
    """`MAPFEnv` over B episodes at once.

    reset(instances=None) -> obs float32 (B, N, C, S, S) (C = 6, 7 with
      `EnvConfig.observation` "cost_to_go")
    step(actions int (B, N)) -> (obs, rewards float32 (B, N), done bool (B,), info) with info
      {"collisions": (B, N), "on_goal": (B, N), "success": (B,), "steps": int (B,)}.
    An episode that is done stays frozen until the next reset: its actions are ignored (treated
    as stay), its rewards are 0, its steps stop counting and `done` stays True.
    Attributes: grids (B, H, W), positions (B, N, 2), goals (B, N, 2), num_envs, num_agents,
    steps (B,), done (B,), last_actions (B, N) (-1 before the first step).
    """

    def __init__(self, instances: Sequence[Instance], config: EnvConfig | None = None,
                 heuristic_cache: HeuristicCache | None = None):
        self.config = config if config is not None else EnvConfig()
        if not isinstance(self.config, EnvConfig):
            raise TypeError(f"config must be an EnvConfig, got {type(self.config).__name__}")
        self._cache = heuristic_cache if heuristic_cache is not None else default_cache
        self._load(instances)
        self.reset()

    def _load(self, instances: Sequence[Instance]) -> None:
        instances = list(instances)
        if not instances:
            raise ValueError("BatchMAPFEnv needs at least one instance")
        for b, inst in enumerate(instances):
            if not isinstance(inst, Instance):
                raise TypeError(f"instances[{b}] must be an Instance, got {type(inst).__name__}")
            if inst.size != instances[0].size or inst.num_agents != instances[0].num_agents:
                raise ValueError(f"instances[{b}] is {inst.size[0]}x{inst.size[1]} with "
                                 f"{inst.num_agents} agents, instances[0] is {instances[0].size[0]}x"
                                 f"{instances[0].size[1]} with {instances[0].num_agents}: a batch "
                                 "needs one map size and agent count")
            inst.validate()
        self.instances = instances
        self.num_envs = len(instances)
        self.num_agents = instances[0].num_agents
        h, w = instances[0].size
        self.grids = np.stack([inst.grid for inst in instances])
        self.goals = np.stack([inst.goals for inst in instances])
        b, n = self.num_envs, self.num_agents
        self._map_of_agent = np.repeat(np.arange(b), n)
        self._map_offset = self._map_of_agent * (h * w)
        self._blocked_flat = (self.grids != 0).reshape(-1)
        self._goal_flat = (self.goals[..., 0] * w + self.goals[..., 1]).reshape(-1)
        distances = None
        guidance = [guidance_for(self.config, inst.grid) for inst in instances]
        if self.config.observation == "cost_to_go":
            distances = np.concatenate([self._cache.distances(inst.grid, inst.goals, g)
                                        for inst, g in zip(instances, guidance)]) \
                if n else np.zeros((0, h, w))
        bits = np.concatenate([self._cache.bits(inst.grid, inst.goals, g)
                               for inst, g in zip(instances, guidance)]) \
            if n else np.zeros((0, h, w), np.uint8)
        self._obs = ObservationBuilder(self.grids, bits, self.config.obs_radius,
                                       self._map_of_agent, distances)

    def _flat_positions(self) -> np.ndarray:
        return self.positions.reshape(-1, 2)

    def _build(self) -> np.ndarray:
        s = self._obs.size
        return self._obs.build(self._flat_positions()).reshape(self.num_envs, self.num_agents,
                                                               self._obs.channels, s, s)

    def reset(self, instances: Sequence[Instance] | None = None) -> np.ndarray:
        if instances is not None:
            self._load(instances)
        self.positions = np.stack([inst.starts for inst in self.instances])
        self.steps = np.zeros(self.num_envs, dtype=np.int64)
        self.done = np.zeros(self.num_envs, dtype=bool)
        self.success = np.zeros(self.num_envs, dtype=bool)
        self.last_actions = np.full((self.num_envs, self.num_agents), -1, dtype=np.int64)
        self._reached = self.on_goal()
        self._obs.set_agents(self._flat_positions())
        return self._build()

    def on_goal(self) -> np.ndarray:
        w = self.grids.shape[2]
        flat = self.positions[..., 0] * w + self.positions[..., 1]
        return flat == self._goal_flat.reshape(self.num_envs, self.num_agents)

    def observe(self) -> np.ndarray:
        return self._build()

    def step(self, actions):
        b, n = self.num_envs, self.num_agents
        actions = np.asarray(actions)
        if actions.shape != (b, n) or not np.issubdtype(actions.dtype, np.integer):
            raise ValueError(f"actions must be integers of shape ({b}, {n}), got "
                             f"{actions.dtype} {actions.shape}")
        bad = (actions < 0) | (actions >= NUM_ACTIONS)
        if bad.any():
            e, i = np.argwhere(bad)[0]
            raise ValueError(f"episode {e} agent {i} action {int(actions[e, i])} is not in "
                             f"0..{NUM_ACTIONS - 1}")
        active = ~self.done
        actions = np.where(active[:, None], actions, STAY).astype(np.int64)
        h, w = self.grids.shape[1:]
        was_on_goal = self.on_goal()
        nxt, collided = _resolve_flat(self._blocked_flat, h, w, self._flat_positions(),
                                      actions.reshape(-1), self._map_offset)
        new_positions = np.stack(np.divmod(nxt, w), axis=1)
        collided = collided.reshape(b, n)
        on_goal = (nxt == self._goal_flat).reshape(b, n)
        first_arrival = on_goal & ~self._reached
        self._reached |= on_goal
        rewards, success = step_rewards(self.config, actions, collided, was_on_goal, on_goal,
                                        first_arrival)
        rewards[~active] = 0.0
        self._obs.move_agents(self._flat_positions(), new_positions)
        self.positions = new_positions.reshape(b, n, 2)
        self.last_actions = np.where(active[:, None], actions, self.last_actions)
        self.steps += active
        self.success |= success & active
        self.done = self.done | self.success | (self.steps >= self.config.max_steps)
        info = {"collisions": collided, "on_goal": on_goal, "success": self.success.copy(),
                "steps": self.steps.copy()}
        return self._build(), rewards, self.done.copy(), info
