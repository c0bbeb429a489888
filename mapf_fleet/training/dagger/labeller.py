"""The expert: who tells DAgger each agent's next move at a visited joint state.

A labeller is anything with `label(state: LabelState) -> Labels` (the `Labeller` protocol): the
rollout hands it the joint state it visited and gets one move per agent back, -1 where it has
none, with a status the run counts. `LaCAMLabeller` (replan from every state, take the first
move) is the one the runs use; `make_labeller` builds the configured one, so another scheme (a
labeller that commits to a plan across steps, say) is a second class and a config value, with the
rollout, shards and learner unchanged. `LabelState.step` lets a labeller that keeps a plan know
where in the episode it is (0 = a new episode)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np

LABEL_STATUSES = ("ok", "unsolved", "too_long")


@dataclass(frozen=True)
class LabelState:
    """One visited joint state of a rollout, as the labeller sees it."""

    grid: np.ndarray  # (H, W), nonzero = obstacle
    positions: np.ndarray  # (N, 2) the agents' cells now
    goals: np.ndarray  # (N, 2)
    distances: np.ndarray  # (N, H, W) BFS distance of every cell to agent i's goal
    step: int  # the episode's step (0 = its first state)
    step_limit: int  # the episode's step limit


class Labels(NamedTuple):
    """`actions` (N,) int64, -1 = no label for that agent; `status` one of LABEL_STATUSES:
    "ok" (every agent labelled), "unsolved" or "too_long" (some agents got none, and why)."""

    actions: np.ndarray
    status: str


class Labeller(Protocol):
    def label(self, state: LabelState) -> Labels: ...


class LaCAMLabeller:
    """Every agent's next move from a joint state: the first step of LaCAM's plan to the goals,
    planned per connected free region (agents of different regions never meet). A region gets no
    labels when LaCAM leaves it unplanned within the limit ("unsolved") or when its plan is longer
    than `plan_limit` ("too_long": a first-found plan far longer than needed spends its first
    moves wandering, a poor label)."""

    def __init__(self, time_limit: float, max_plan_factor: float, max_plan_slack: int,
                 seed: int = 0):
        from mapf_fleet.coordination.planners import ClassicalPlanner

        self.planner = ClassicalPlanner("lacam", time_limit, seed)
        self.max_plan_factor = float(max_plan_factor)
        self.max_plan_slack = int(max_plan_slack)

    def plan_limit(self, lower_bound: int, step_limit: int) -> int:
        """The longest plan whose first moves are used: min(step limit, factor x the longest BFS
        distance of any agent to its goal + slack)."""
        return int(min(step_limit, self.max_plan_factor * lower_bound + self.max_plan_slack))

    def label(self, state: LabelState) -> Labels:
        from mapf_fleet.coordination.planners import positions_to_actions
        from mapf_fleet.grid.instance import free_components

        grid = state.grid
        positions = np.asarray(state.positions, np.int64)
        goals = np.asarray(state.goals, np.int64)
        labels = np.full(len(positions), -1, np.int64)
        region = free_components(np.asarray(grid) != 0)[positions[:, 0], positions[:, 1]]
        status = "ok"
        for value in np.unique(region):
            idx = np.flatnonzero(region == value)
            if np.array_equal(positions[idx], goals[idx]):
                labels[idx] = 0  # all on their goals: stay
                continue
            result = self.planner.plan(grid, positions[idx], goals[idx])
            if not result.complete:
                status = "unsolved"
                continue
            lower = int(state.distances[idx, positions[idx, 0], positions[idx, 1]].max())
            if len(result.positions) - 1 > self.plan_limit(lower, state.step_limit):
                status = "too_long" if status == "ok" else status
                continue
            labels[idx] = positions_to_actions(result.positions[:2])[0]
        return Labels(labels, status)


def make_labeller(cfg) -> Labeller:
    """The labeller a DAgger config asks for."""
    return LaCAMLabeller(cfg.label_time_limit, cfg.max_plan_factor, cfg.max_plan_slack,
                         cfg.planner_seed)
