"""DAgger's committed expert: labels that add up to one kept plan.

`CommittedExpert` gives, for a state, every agent's next move from a kept plan (re-planning, with
the kept plan's next moves ranked first at the root for the agents still on it, only when some
agent left it or every k steps) and the plan's remaining trajectory: an expert whose labels add
up to one plan, instead of a fresh plan's first move every step (independent re-plans oscillate
in closed loop: docs/results.md, "The expert ceiling"). It drives a
`coordination.plan.PlanKeeper` (options `plan.EXPERT`) through the keeper's public surface.
"""

from __future__ import annotations

import numpy as np

from mapf_fleet.coordination.factory import make_shield
from mapf_fleet.coordination.plan import EXPERT, PlanKeeper, distance_rankings
from mapf_fleet.coordination.rules import Rule
from mapf_fleet.grid.actions import actions_between


class CommittedExpert:
    """An expert that commits to a plan: `moves(positions)` gives every agent's next action from
    the kept plan. When some agents are not where the plan put them (the policy moved them
    elsewhere), it re-plans from the state with the kept plan's next moves ranked first at the
    root for the agents still on it (distance order for the others), so their labels stay on
    the plan where LaCAM's first step can keep them; it also re-plans every `replan_every`
    steps (0: never). When no plan is found in the budget, the labels are the anchored PIBT
    step's (`fallback` is True in `last`).

    The expert does not advance with the executed moves: call `moves` once with each state the
    rollout visits (it follows the plan's index while the agents stay on it; a state that is not
    the one the last labels lead to is off the plan).

    rule: the PIBT rule its labels will run under (`pibt_anchor_swap`, ...; None: not known),
    anchor_patience: its anchor's patience. Given the rule's state at the visited state
    (`moves(positions, rule.snapshot())`),
    the expert first asks a copy of the rule what it would execute for its labels; where that
    leaves the plan (the anchored top agent's distance order, a swap), it re-plans from the
    state with the rule's priorities and the top agent's anchored ranking at LaCAM's root, so
    the new plan's first step is one the rule lets through (`last["rule_replan"]`)."""

    def __init__(self, grid, goals, planning_budget: float | None = None,
                 replan_every: int | None = None, max_nodes: int | None = None,
                 seed: int | None = None, swap: bool | None = None,
                 rule: "Rule | str | None" = None, anchor_patience: int | None = None,
                 restarts: int | None = None, guidance=None):
        self.keeper = PlanKeeper(grid, goals, EXPERT, guidance=guidance,
                                 planning_budget=planning_budget, replan_every=replan_every,
                                 max_nodes=max_nodes, seed=seed, swap=swap, restarts=restarts)
        self.rule = None
        if rule is not None:
            rule = Rule.parse(rule, "rule")
            if not rule.is_pibt:
                raise ValueError(f"rule must be a PIBT rule, got {rule.name!r}")
            # the rollout's own arbiter (an `_epibt` rule's is an EPIBTShield)
            self.rule = make_shield(rule, grid, goals, anchor_patience=anchor_patience,
                                    guidance=guidance)
        self.last: dict = {}
        self._expect: int | None = None  # the plan index the next state should be at

    @property
    def goals(self) -> np.ndarray:
        return self.keeper.goals

    def set_goals(self, goals) -> np.ndarray:
        if self.rule is not None:
            self.rule.set_goals(goals)
        return self.keeper.set_goals(goals)

    def reset(self) -> None:
        self.keeper.reset()
        self._expect = None

    def _locate(self, positions) -> int:
        """The index of the kept plan's configuration the planned agents are at: the one the
        last labels lead to (the rollout followed them), or the current one right after a
        (re-)plan; -1 otherwise. A state that did not advance while the plan moves someone
        counts as off the plan: the executed step did not follow the labels (a shield
        overriding them), and labelling it again would repeat the same labels forever."""
        keeper = self.keeper
        plan = keeper.plan
        if plan is None:
            return -1
        planned = ~keeper.unplanned
        t = keeper.index if self._expect is None else self._expect
        return t if np.array_equal(plan[t][planned], positions[planned]) else -1

    def moves(self, positions, rule_state: dict | None = None) -> np.ndarray:
        """(N,) every agent's next action (DHC order) at `positions` (N, 2); with the rule's
        state there (`PIBTShield.snapshot()`, see the class), labels the rule lets through
        where it can."""
        informed = self.rule is not None and rule_state is not None
        if informed:  # a re-plan starts from the rule's priorities (LaCAM's root order)
            self.keeper.priorities = np.asarray(rule_state["priorities"], np.float64).copy()
        actions = self._moves(positions)
        if not informed or self.keeper.plan is None:
            return actions
        keeper, rule = self.keeper, self.rule
        positions = np.asarray(positions, dtype=np.int64)
        rule.restore(rule_state)
        rankings = self._label_rankings(positions, actions)
        if np.array_equal(self._rule_step(positions, rankings), keeper.next_cells()):
            self.last["rule_replan"] = False
            return actions
        # the rule would leave the plan: plan again from here with the rule's priorities and
        # its anchored top agent's ranking at the root (the first step the rule would take)
        top = rule.anchored_agent()
        if top >= 0:
            flat = int(positions[top, 0] * keeper.width + positions[top, 1])
            rankings[top] = rule.anchored_ranking(top, flat)
        old = keeper.saved()
        found = keeper.replan(positions, rankings)
        self.last["rule_replan"] = True
        if not found and keeper.plan is None:
            keeper.restore(old)  # keep the labels we had
            return actions
        self._expect = min(keeper.index + 1, len(keeper.plan) - 1)
        return self._actions(positions, rankings)

    def _label_rankings(self, positions, actions) -> np.ndarray:
        """Every agent's label first, then its distance order (as a rollout ranks a label)."""
        rankings = distance_rankings(self.rule, positions)
        for i, first in enumerate(np.asarray(actions).tolist()):
            if rankings[i, 0] != first:
                rankings[i] = [first] + [a for a in rankings[i].tolist() if a != first]
        return rankings

    def _rule_step(self, positions, rankings) -> np.ndarray:
        """The cells the rule would command for these rankings (its state left as it was)."""
        return self.rule.peek(positions, rankings).positions

    def _moves(self, positions) -> np.ndarray:
        keeper = self.keeper
        positions = keeper.fallback.check_positions(positions)
        t = self._locate(positions)
        periodic = keeper.replan_every and t >= 0 and t >= keeper.replan_every
        if t >= 0:
            keeper.index = t  # where the state is (a failed periodic re-plan resumes here)
        if t >= 0 and not periodic:
            self._expect = min(t + 1, len(keeper.plan) - 1)
            self.last = {"replanned": False, "fallback": bool(keeper.unplanned.any()),
                         "on_plan": int((~keeper.unplanned).sum())}
            return self._actions(positions)
        rankings = distance_rankings(keeper, positions)
        on_plan = np.zeros(keeper.num_agents, dtype=bool)
        if keeper.plan is not None:
            # the agents standing where the kept plan expected them (one step on from the last
            # labelled state) keep their next planned move first
            plan = keeper.plan
            expected = min(keeper.index + 1, len(plan) - 1)
            on_plan = (plan[expected] == positions).all(axis=1) & ~keeper.unplanned
            firsts = actions_between(positions, plan[min(expected + 1, len(plan) - 1)])
            for i in np.flatnonzero(on_plan).tolist():
                first = int(firsts[i])
                rankings[i] = [first] + [a for a in rankings[i].tolist() if a != first]
        old = keeper.saved()
        found = keeper.replan(positions, rankings)
        if not found and periodic:
            keeper.restore(old)
            found = True
        self.last = {"replanned": True, "fallback": not found, "on_plan": int(on_plan.sum())}
        if keeper.plan is None:
            self._expect = None
            return keeper.fallback.step(positions, rankings).actions
        self._expect = min(keeper.index + 1, len(keeper.plan) - 1)
        return self._actions(positions, rankings)

    def _actions(self, positions, rankings=None) -> np.ndarray:
        """The plan's next moves; the anchored PIBT step's for agents without a plan."""
        keeper = self.keeper
        nxt = keeper.next_cells().copy()
        if keeper.unplanned.any():
            if rankings is None:
                rankings = distance_rankings(keeper, positions)
            # the fallback's step for the agents without a plan, the rule's state untouched
            # (this only labels; the rollout's own rule takes the tick)
            pibt = keeper.fallback.peek(positions, rankings)
            nxt[keeper.unplanned] = pibt.positions[keeper.unplanned]
        return actions_between(positions, nxt)

    def trajectory(self) -> np.ndarray | None:
        """The kept plan's remaining trajectory (T'+1, N, 2) from the configuration of the last
        `moves` call, or None."""
        return self.keeper.remaining_plan()


__all__ = ["CommittedExpert"]
