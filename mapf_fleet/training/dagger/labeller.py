"""The expert: who tells DAgger each agent's next move at a visited joint state.

A labeller is anything with `label(state: LabelState) -> Labels` (the `Labeller` protocol): the
rollout hands it the joint state it visited and gets one move per agent back, -1 where it has
none, with a status the run counts. Schemes (`LABELLERS`, the config's `labeller`):
- "lacam" (`LaCAMLabeller`): LaCAM (pymapf) from every labelled state, the first move of its plan;
- "committed" (`CommittedLabeller`): the policy's states labelled from one kept plan
  (`coordination.plan.CommittedExpert`, the project's LaCAM), re-planned only for a state off the
  plan, a new goal, or every `committed_replan_every` states: labels that add up to one plan
  (`committed_planner: pymapf`: `KeptPyMAPFLabeller`, the same over pymapf's LaCAM);
- "stuck" (`StuckLabeller`): no labels while the rollout progresses; from the state where it
  stopped progressing (`stuck_window`), the committed expert's whole trajectory.
`make_labeller` builds the configured one; the rollout, shards and learner do not depend on the
scheme. `LabelState.step` lets a labeller that keeps a plan know where in the episode it is
(0 = a new episode). `mapf-fleet dagger --expert-ceiling` (`ceiling.py`) measures a scheme as the
policy itself."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np

LABEL_STATUSES = ("ok", "unsolved", "too_long", "skipped")


@dataclass(frozen=True)
class LabelState:
    """One visited joint state of a rollout, as the labeller sees it."""

    grid: np.ndarray  # (H, W), nonzero = obstacle
    positions: np.ndarray  # (N, 2) the agents' cells now
    goals: np.ndarray  # (N, 2)
    distances: np.ndarray  # (N, H, W) BFS distance of every cell to agent i's goal
    step: int  # the episode's step (0 = its first state)
    step_limit: int  # the episode's step limit
    # the conflict rule's state at this state (`PIBTShield.snapshot()`; None: not a PIBT rule):
    # an expert that knows it labels moves the rule lets through (CommittedExpert's `rule`)
    rule_state: dict | None = None


class Labels(NamedTuple):
    """`actions` (N,) int64, -1 = no label for that agent; `status` one of LABEL_STATUSES:
    "ok" (every agent labelled), "unsolved" or "too_long" (some agents got none, and why),
    "skipped" (the scheme labels no agent at this state by design: no back-off)."""

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


class CommittedLabeller:
    """Labels from a kept plan: `coordination.plan.CommittedExpert` (one per episode, made at
    its first state) gives every agent the kept plan's next move; it re-plans (the kept plan's
    next moves ranked first at the root for the agents still on it) when the state is not where
    the plan leads, when a goal changed (lifelong), or every `replan_every` states (0: never),
    with `planning_budget` seconds of wall clock per re-plan. Agents the plan leaves out (no plan
    found in the budget for their region) get no label ("unsolved"): the expert's own fallback
    there is plain PIBT's step, not worth imitating. swap: LaCAM's successors by PIBT with swap;
    max_nodes: LaCAM's node budget per re-plan (a budget that does not depend on the machine's
    load, where the wall-clock budget does); restarts: LaCAM searches per re-plan (seeds seed,
    seed + 1, ...), the shortest plan kept; rule: the rollout's PIBT rule, whose priorities
    and tick the states carry (`LabelState.rule_priorities`): labels the rule lets through
    (`CommittedExpert`'s `rule`)."""

    def __init__(self, planning_budget: float, replan_every: int = 0, seed: int = 0,
                 swap: bool = False, max_nodes: int = 1_000_000, rule: str | None = None,
                 anchor_patience: int | None = None, restarts: int = 1):
        self.planning_budget = float(planning_budget)
        self.replan_every = int(replan_every)
        self.seed = int(seed)
        self.swap = bool(swap)
        self.max_nodes = int(max_nodes)
        self.rule = rule  # the rollout's PIBT rule, when the expert is to label for it
        self.anchor_patience = anchor_patience  # None: the rule's
        self.restarts = int(restarts)
        self.expert = None
        self._grid = None
        self.replans = 0  # re-plans since construction (the ceiling reports them per episode)

    def label(self, state: LabelState) -> Labels:
        from .expert import CommittedExpert

        if self.expert is None or state.step == 0 or state.grid is not self._grid:
            self.expert = CommittedExpert(state.grid, state.goals,
                                          planning_budget=self.planning_budget,
                                          replan_every=self.replan_every, seed=self.seed,
                                          swap=self.swap, max_nodes=self.max_nodes,
                                          rule=self.rule,
                                          anchor_patience=self.anchor_patience,
                                          restarts=self.restarts)
            self._grid = state.grid
        elif not np.array_equal(self.expert.goals, state.goals):
            self.expert.set_goals(state.goals)
        actions = np.asarray(self.expert.moves(state.positions, state.rule_state),
                             np.int64).copy()
        self.replans += bool(self.expert.last.get("replanned"))
        keeper = self.expert.keeper
        if keeper.plan is None:
            return Labels(np.full(len(actions), -1, np.int64), "unsolved")
        if keeper.unplanned.any():
            actions[keeper.unplanned] = -1
            return Labels(actions, "unsolved")
        return Labels(actions, "ok")


class KeptPyMAPFLabeller:
    """The committed scheme over pymapf's LaCAM (`coordination.planners.ClassicalPlanner`, the
    per-step labeller's planner): one plan kept while the visited states follow it (each state
    is the configuration the last labels lead to), re-planned from the state otherwise; its next moves are the labels. No plan in the budget
    (`time_limit` seconds per connected region): no labels ("unsolved")."""

    def __init__(self, time_limit: float, seed: int = 0):
        from mapf_fleet.coordination.planners import ClassicalPlanner

        self.planner = ClassicalPlanner("lacam", time_limit, seed)
        self.seed = int(seed)
        self.plan, self.index, self._grid, self._goals = None, 0, None, None
        self.replans = 0

    def label(self, state: LabelState) -> Labels:
        from mapf_fleet.coordination.planners import positions_to_actions

        positions = np.asarray(state.positions, np.int64)
        if (state.step == 0 or state.grid is not self._grid
                or not np.array_equal(self._goals, state.goals)):
            self.plan = None
            self._grid, self._goals = state.grid, np.asarray(state.goals).copy()
        if self.plan is not None:
            at = min(self.index + 1, len(self.plan) - 1)
            if np.array_equal(self.plan[at], positions):
                self.index = at
            else:  # off the plan (also a state that did not advance: the rule refused it)
                self.plan = None
        if self.plan is None:
            result = self.planner.plan(state.grid, positions, state.goals)
            self.replans += 1
            if not result.complete:
                return Labels(np.full(len(positions), -1, np.int64), "unsolved")
            self.plan, self.index = np.asarray(result.positions), 0
        nxt = self.plan[min(self.index + 1, len(self.plan) - 1)]
        return Labels(positions_to_actions(np.stack([positions, nxt]))[0], "ok")


class StuckLabeller:
    """Whole expert trajectories from the state where the rollout got stuck: no labels
    ("skipped") while the rollout makes progress; once the sum over agents of the BFS distance
    to their goals has not reached a new low for `window` labelled states, a committed expert
    (`CommittedLabeller`) plans from that state and labels every later state of the episode from
    its kept plan (re-planning as it does). The labels concentrate where the policy fails; as
    the policy (the ceiling), it is plain PIBT until stuck, then the expert."""

    def __init__(self, planning_budget: float, replan_every: int = 0, seed: int = 0,
                 window: int = 8, swap: bool = False, max_nodes: int = 1_000_000,
                 rule: str | None = None, anchor_patience: int | None = None,
                 restarts: int = 1):
        if int(window) < 1:
            raise ValueError(f"stuck window must be >= 1 state, got {window!r}")
        self.committed = CommittedLabeller(planning_budget, replan_every, seed, swap, max_nodes,
                                           rule, anchor_patience, restarts)
        self.window = int(window)
        self.seed = int(seed)
        self._best, self._since, self.active_from = None, 0, None

    @property
    def replans(self) -> int:
        return self.committed.replans

    def label(self, state: LabelState) -> Labels:
        if state.step == 0 or self._best is None:
            self._best, self._since, self.active_from = None, 0, None
        if self.active_from is None:
            pos = np.asarray(state.positions, np.int64)
            total = int(state.distances[np.arange(len(pos)), pos[:, 0], pos[:, 1]].sum())
            if self._best is None or total < self._best:
                self._best, self._since = total, 0
            else:
                self._since += 1
            if self._since < self.window:
                return Labels(np.full(len(pos), -1, np.int64), "skipped")
            self.active_from = state.step
            self.committed.expert = None  # a fresh plan from the stuck state
        return self.committed.label(state)


LABELLERS = ("lacam", "committed", "stuck")


def make_labeller(cfg, seed: int | None = None) -> Labeller:
    """The labeller a DAgger config asks for (`labeller`); `seed` replaces the planner's seed
    (the ceiling's self-agreement labels the same states with a second seed)."""
    seed = cfg.planner_seed if seed is None else int(seed)
    rule = cfg.conflict_rule if cfg.committed_follow_rule else None
    if cfg.labeller == "committed" and cfg.committed_planner == "pymapf":
        return KeptPyMAPFLabeller(cfg.committed_budget, seed)
    if cfg.labeller == "committed":
        return CommittedLabeller(cfg.committed_budget, cfg.committed_replan_every, seed,
                                 cfg.committed_swap, cfg.committed_max_nodes, rule,
                                 cfg.anchor_patience, cfg.committed_restarts)
    if cfg.labeller == "stuck":
        return StuckLabeller(cfg.committed_budget, cfg.committed_replan_every, seed,
                             cfg.stuck_window, cfg.committed_swap, cfg.committed_max_nodes, rule,
                             cfg.anchor_patience, cfg.committed_restarts)
    return LaCAMLabeller(cfg.label_time_limit, cfg.max_plan_factor, cfg.max_plan_slack, seed)
