"""Per-episode metrics of the paper's protocol and their aggregation per scenario.

Definitions (one episode of N agents with step limit L; a "step" is one joint action of all
agents, the conflict rules of `mapf_fleet.grid.env` applied):

- **success**: at some step t <= L every agent stands on its own goal (the episode ends there,
  as in the DHC/DCC reference environments).
- **steps** (the paper's "average time steps" before averaging): t for a success, L for a failure.
- **agent success**: the fraction of agents standing on their goals at the episode's last step.
- **cost of agent i** c_i: the step after which agent i stays on its goal until the episode ends
  (its last arrival; 0 if it starts there and never leaves); L if it is not on its goal at the end.
- **sum of costs**: sum_i c_i. **makespan**: max_i c_i (equals `steps` for a success, L otherwise).
- **collisions**: the number of reverted moves (`info["collisions"]` summed over agents and
  steps); an agent whose move is reverted counts once per step.
- **lower bound**: max_i d(s_i, g_i), the longest single-agent shortest path (BFS over the static
  obstacles, other agents ignored); no solution can finish earlier.
- **lower-bound ratio**: steps / lower bound (failures at L, as the paper's average steps).
  The summary also gives the ratio over solved episodes only, which measures path quality
  without mixing in the time-outs.
- **stalled agents**: agents off their goal at the episode's end that have not changed cell in
  its last `STALL_STEPS` steps; **stalled beside an agent**: those of them with another agent in
  one of their four neighbouring cells at the end. They measure the failure mode the paper names
  (deadlocks: agents waiting on each other, or on an agent parked on its goal, until the limit)
  apart from agents that wander or lose their way.
- **overrides** (under a shield, `--conflict-rule pibt`): per episode, the agent-steps whose executed
  action was not the agent's first choice (the coordination layer moved or held it). 0 without a
  shield, where reverted moves count as collisions instead.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

STALL_STEPS = 32  # an agent that has not moved for this long at the end is stalled


@dataclass(frozen=True)
class EpisodeRecord:
    """The measured outcome of one episode (see the module docstring for each definition)."""

    success: bool
    steps: int
    max_steps: int
    num_agents: int
    agents_on_goal: int
    sum_of_costs: int
    makespan: int
    collisions: int
    lower_bound: int
    stalled_agents: int = 0
    stalled_beside_agent: int = 0
    overrides: int = 0

    @property
    def agent_success(self) -> float:
        return self.agents_on_goal / self.num_agents

    @property
    def lower_bound_ratio(self) -> float:
        # A lower bound of 0 means every agent starts on its goal: the ratio is then 1 by
        # convention (nothing to do, nothing wasted).
        return self.steps / self.lower_bound if self.lower_bound > 0 else 1.0

    def to_dict(self) -> dict:
        out = asdict(self)
        out["agent_success"] = self.agent_success
        out["lower_bound_ratio"] = self.lower_bound_ratio
        return out


class EpisodeTracker:
    """Accumulates the metrics of one episode step by step, without storing the trajectory.

    `update(positions, collided)` is called after every joint step with the positions after the
    step and the bool (N,) mask of reverted moves; `record()` closes the episode.
    """

    def __init__(self, starts: np.ndarray, goals: np.ndarray, max_steps: int, lower_bound: int):
        starts = np.asarray(starts)
        self.goals = np.asarray(goals)
        if starts.shape != self.goals.shape or starts.ndim != 2 or starts.shape[1] != 2:
            raise ValueError(f"starts {starts.shape} and goals {self.goals.shape} must both be (N, 2)")
        if max_steps <= 0:
            raise ValueError(f"max_steps must be positive, got {max_steps}")
        self.max_steps = int(max_steps)
        self.lower_bound = int(lower_bound)
        self.steps = 0
        self.collisions = 0
        self.overrides = 0
        self.on_goal = np.all(starts == self.goals, axis=1)
        # Step at which each agent last stepped onto its goal (valid where on_goal).
        self.arrival = np.zeros(len(starts), dtype=np.int64)
        self.success = bool(self.on_goal.all())
        self.positions = starts.copy()
        self.last_moved = np.zeros(len(starts), dtype=np.int64)  # step of each agent's last move

    @property
    def done(self) -> bool:
        return self.success or self.steps >= self.max_steps

    def update(self, positions: np.ndarray, collided: np.ndarray, overridden=None) -> None:
        if self.done:
            raise RuntimeError("update() after the episode ended")
        self.steps += 1
        self.collisions += int(np.count_nonzero(collided))
        if overridden is not None:
            self.overrides += int(np.count_nonzero(overridden))
        positions = np.asarray(positions)
        self.last_moved[np.any(positions != self.positions, axis=1)] = self.steps
        self.positions = positions.copy()
        now_on_goal = np.all(positions == self.goals, axis=1)
        self.arrival[now_on_goal & ~self.on_goal] = self.steps
        self.on_goal = now_on_goal
        self.success = bool(now_on_goal.all())

    def record(self) -> EpisodeRecord:
        costs = np.where(self.on_goal, self.arrival, self.max_steps)
        stalled = ~self.on_goal & (self.steps - self.last_moved >= STALL_STEPS)
        # another agent in a 4-neighbouring cell (Manhattan distance 1) at the end
        distance = np.abs(self.positions[:, None, :] - self.positions[None, :, :]).sum(-1)
        beside = stalled & np.any(distance == 1, axis=1)
        return EpisodeRecord(
            success=self.success,
            steps=self.steps if self.success else self.max_steps,
            max_steps=self.max_steps,
            num_agents=len(self.goals),
            agents_on_goal=int(self.on_goal.sum()),
            sum_of_costs=int(costs.sum()),
            makespan=int(costs.max()),
            collisions=self.collisions,
            lower_bound=self.lower_bound,
            stalled_agents=int(stalled.sum()),
            stalled_beside_agent=int(beside.sum()),
            overrides=self.overrides,
        )


def episode_from_trajectory(
    positions: np.ndarray, goals: np.ndarray, collided: np.ndarray, max_steps: int, lower_bound: int
) -> EpisodeRecord:
    """Metrics of a recorded trajectory: `positions` (T+1, N, 2) from the start, `collided`
    (T, N). The trajectory must stop at the first success or at the limit."""
    positions = np.asarray(positions)
    collided = np.asarray(collided, dtype=bool)
    if positions.ndim != 3 or len(collided) != len(positions) - 1:
        raise ValueError(f"positions {positions.shape} must be (T+1, N, 2) and collided (T, N), got {collided.shape}")
    tracker = EpisodeTracker(positions[0], goals, max_steps, lower_bound)
    for t in range(1, len(positions)):
        tracker.update(positions[t], collided[t - 1])
    return tracker.record()


@dataclass(frozen=True)
class ScenarioSummary:
    """Averages over the episodes of one (policy, scenario) cell of the tables."""

    episodes: int
    success_rate: float
    average_steps: float
    agent_success_rate: float
    sum_of_costs: float
    makespan: float
    collisions: float
    lower_bound: float
    lower_bound_ratio: float
    lower_bound_ratio_solved: float  # NaN when no episode succeeded
    stalled_agents: float = float("nan")  # per episode (NaN: records from before it was measured)
    stalled_beside_agent: float = float("nan")
    overrides: float = 0.0  # per episode: agent-steps not executed as first chosen (shield)

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in asdict(self).items()}


def summarize(records: list[EpisodeRecord]) -> ScenarioSummary:
    """Paper metrics: success rate = solved / episodes; average steps = mean of `steps` with
    failures at the limit. The other fields are plain means over the episodes."""
    if not records:
        raise ValueError("summarize() needs at least one episode")

    def mean(values) -> float:
        values = list(values)
        return float(np.mean(values)) if values else float("nan")

    return ScenarioSummary(
        episodes=len(records),
        success_rate=mean(r.success for r in records),
        average_steps=mean(r.steps for r in records),
        agent_success_rate=mean(r.agent_success for r in records),
        sum_of_costs=mean(r.sum_of_costs for r in records),
        makespan=mean(r.makespan for r in records),
        collisions=mean(r.collisions for r in records),
        lower_bound=mean(r.lower_bound for r in records),
        lower_bound_ratio=mean(r.lower_bound_ratio for r in records),
        lower_bound_ratio_solved=mean(r.lower_bound_ratio for r in records if r.success),
        stalled_agents=mean(r.stalled_agents for r in records),
        stalled_beside_agent=mean(r.stalled_beside_agent for r in records),
        overrides=mean(r.overrides for r in records),
    )
