"""The plan keeper: a committed joint plan executed tick by tick (the `lacam` conflict rule), and
the committed expert that labels from the same kept plan.

`PlanKeeper` keeps a LaCAM plan (`coordination.lacam`, the robots' rankings ranking the root
step's moves) and commands its next step every tick. It re-plans from the current state only when
something leaves the plan:
- a new goal (`set_goals`: lifelong streams, tasks, goals at run time),
- a held robot (`fixed`, or standing on a reserved cell) that the plan moves this tick, or a
  plan step into a reserved cell,
- a robot not where the plan put it (a missed decision, a robot the arbiter did not command),
- every `replan_every` ticks when asked (0: never; a failed periodic re-plan keeps the old plan).
Each re-plan gets `planning_budget` seconds of wall clock. When the planner finds no plan in it,
the tick falls back to the anchored PIBT step (`fallback_rule`: `pibt_anchor`, and for the
`lacam` rule `pibt_anchor_swap`) over the robots' rankings (only for the robots of the free
regions without a plan: regions never meet), and the planner tries again next tick, then after
2, 4, ... ticks while it keeps failing (at most `max_retry_interval`): the tick time is bounded
by the budget, an unsolvable crowd does not cost it every tick, and every tick keeps PIBT's
guarantees. Robots sharing a goal cell plan towards distinct cells (`planning_goals`).

Guarantees of `PlanKeeper.step` (property-tested), as `PIBTShield.step`: no two agents in one
cell, no two agents trading cells, no agent on an obstacle or off the map, every agent moves at
most one cell, a `fixed` agent stays and `reserved` cells stay free. A plan step satisfies them by
construction (LaCAM's plans are checked valid, and a re-plan holds the fixed agents and keeps
the reserved cells free on its first step); a fallback step is PIBT's.

Priorities: the keeper's PIBT priorities (`priorities`, `base_priority`, `advance_priorities`)
advance every tick as the shield's do; a re-plan starts LaCAM from them, so a robot that has
waited long leads the plan's first step, and the fallback step uses them.

`CommittedExpert` gives, for a state, every agent's next move from a kept plan (re-planning, with
the kept plan's next moves ranked first at the root for the agents still on it, only when some
agent left it or every k steps) and the plan's remaining trajectory: an expert whose labels add
up to one plan, instead of a fresh plan's first move every step.

numpy only, as `pibt`.
"""

from __future__ import annotations

import time

import numpy as np

from mapf_fleet.grid.actions import NUM_ACTIONS

from .lacam import LaCAM
from .pibt import PIBTShield, ShieldStep, rule_options, validate_rankings

# The planning arbiter's default per-tick planning budget (seconds of wall clock)
DEFAULT_PLANNING_BUDGET = 1.0
# After a failed planner call the next waits 1, 2, 4, ... ticks, at most this many
DEFAULT_MAX_RETRY_INTERVAL = 16


class PlanKeeper:
    """The `lacam` conflict rule: the interface of `PIBTShield` (`step`, `set_goals`, `reset`,
    `advance_priorities`, `goals`, `priorities`, `base_priority`, `tick`) over a kept LaCAM plan.

    grid: (H, W), nonzero = obstacle. goals: (N, 2). planning_budget: seconds per re-plan.
    replan_every: re-plan every k ticks even when the plan holds (0: only when it breaks).
    max_nodes: LaCAM's node budget per call. seed: LaCAM's tie-breaking seed.
    max_retry_interval: the longest wait (ticks) between tries after failed calls.
    swap: LaCAM's successors by PIBT with swap (`LaCAM(swap=True)`). restarts: LaCAM searches
    per re-plan, the shortest plan kept (`_call_planner`). shared_budget: the restarts share one
    `planning_budget` (a re-plan costs at most about the budget: the arbiter) instead of one
    each (the committed expert, whose labels a node budget bounds). restart_ratio: restart only
    while the shortest plan so far is longer than this many times the longest agent's distance
    to its goal (0: always; a first plan that misses a step limit is 2-8 times it).
    streamed_restarts: restart also once the goals have changed (a lifelong stream: every
    arrival re-plans and the plan is dropped at the next one; restarting there cost the arbiter
    2-3.5 times the run time and gained nothing; docs/results.md). fallback_rule: the PIBT rule
    of the ticks without a plan (`pibt_anchor`; the `lacam` conflict rule: `pibt_anchor_swap`)."""

    def __init__(self, grid, goals, planning_budget: float = DEFAULT_PLANNING_BUDGET,
                 replan_every: int = 0, max_nodes: int = 1_000_000, seed: int = 0,
                 max_retry_interval: int = DEFAULT_MAX_RETRY_INTERVAL, swap: bool = False,
                 restarts: int = 1, shared_budget: bool = False, restart_ratio: float = 0.0,
                 streamed_restarts: bool = True, fallback_rule: str = "pibt_anchor"):
        if not planning_budget > 0:
            raise ValueError(f"planning_budget must be a positive number of seconds, got "
                             f"{planning_budget!r}")
        if int(replan_every) < 0:
            raise ValueError(f"replan_every must be >= 0 (0: never), got {replan_every!r}")
        options = rule_options(fallback_rule)
        if not options["anchor"]:
            # the anchor is what makes the fallback reach every goal (coordination.pibt)
            raise ValueError(f"fallback_rule must be an anchored PIBT rule, got {fallback_rule!r}")
        self.fallback = PIBTShield(grid, goals, **options)
        self.grid = self.fallback.grid
        self.height, self.width = self.grid.shape
        self.num_agents = self.fallback.num_agents
        self.planner = LaCAM(self.grid, seed=seed, swap=swap)
        self.planning_budget = float(planning_budget)
        self.replan_every = int(replan_every)
        self.max_nodes = int(max_nodes)
        if int(restarts) < 1:
            raise ValueError(f"restarts must be >= 1, got {restarts!r}")
        self.restarts = int(restarts)
        self.shared_budget = bool(shared_budget)
        if not float(restart_ratio) >= 0:
            raise ValueError(f"restart_ratio must be >= 0, got {restart_ratio!r}")
        self.restart_ratio = float(restart_ratio)
        self.streamed_restarts = bool(streamed_restarts)
        self.streamed = False  # the goals changed since the episode began
        if int(max_retry_interval) < 1:
            raise ValueError(f"max_retry_interval must be >= 1 tick, got {max_retry_interval!r}")
        self.max_retry_interval = int(max_retry_interval)
        self.plan: np.ndarray | None = None  # (T+1, N, 2), plan[self.index] = where we are
        self.index = 0
        self.unplanned = np.zeros(self.num_agents, dtype=bool)  # agents the plan leaves out
        self._retry_at, self._retry_interval = 0, 1
        self._subset = slice(None)
        self.anchor = True
        self.reset_counters()

    # --- the PIBTShield interface ------------------------------------------------------------
    @property
    def goals(self) -> np.ndarray:
        return self.fallback.goals

    @property
    def priorities(self) -> np.ndarray:
        return self.fallback.priorities

    @priorities.setter
    def priorities(self, value) -> None:
        self.fallback.priorities = value

    @property
    def base_priority(self) -> np.ndarray:
        return self.fallback.base_priority

    @property
    def tick(self) -> int:
        return self.fallback.tick

    def distance_map(self, agent: int) -> np.ndarray:
        return self.fallback.distance_map(agent)

    def reset(self) -> None:
        """A new episode: priorities back to their tie-breakers, no plan."""
        self.fallback.reset()
        self.plan = None
        self.index = 0
        self._retry_at, self._retry_interval = 0, 1
        self.streamed = False

    def set_goals(self, goals) -> np.ndarray:
        """New goals (N, 2); the plan is dropped when any changed (`PIBTShield.set_goals`) and
        made again at the next tick (or, after a failed call, at its retry tick)."""
        changed = self.fallback.set_goals(goals)
        if changed.any():
            # re-planned at the next tick, unless the last call failed: then at its retry tick
            # (lifelong streams change goals nearly every tick; a crowd the planner cannot
            # solve would otherwise cost the whole budget every tick)
            self.plan = None
            self.counters["goal_changes"] += 1
            self.streamed = True
        return changed

    def advance_priorities(self, positions) -> None:
        """As `PIBTShield.advance_priorities`; a tick where everyone was held leaves the plan
        where it was (the robots are still where it put them)."""
        self.fallback.advance_priorities(positions)

    # --- counters ----------------------------------------------------------------------------
    def reset_counters(self) -> None:
        self.counters = {"ticks": 0, "planner_calls": 0, "planner_seconds": 0.0,
                         "planner_max_seconds": 0.0, "planned_ticks": 0, "fallback_ticks": 0,
                         "fallback_agent_ticks": 0,
                         "tick_seconds": 0.0, "tick_max_seconds": 0.0, "goal_changes": 0,
                         "repairs_held": 0, "repairs_off_plan": 0, "repairs_periodic": 0,
                         "plans_found": 0}

    def stats(self) -> dict:
        """The counters plus the rates: mean planner seconds per call and per tick, fallback
        rate (fallback ticks / ticks)."""
        c = dict(self.counters)
        ticks = max(c["ticks"], 1)
        c["planner_seconds_per_call"] = c["planner_seconds"] / max(c["planner_calls"], 1)
        c["tick_seconds_mean"] = c["tick_seconds"] / ticks
        c["fallback_rate"] = c["fallback_ticks"] / ticks
        return c

    # --- the kept plan -----------------------------------------------------------------------
    def remaining_plan(self) -> np.ndarray | None:
        """The kept plan from the current configuration on, (T'+1, N, 2), or None."""
        return None if self.plan is None else self.plan[self.index:].copy()

    def _next_cells(self) -> np.ndarray:
        plan = self.plan
        return plan[min(self.index + 1, len(plan) - 1)]

    def why_replan(self, positions, fixed, reserved_flat) -> str:
        """"" when the kept plan holds for this state, else the reason to plan: "no plan",
        "off plan", "held", "periodic", or "unplanned" (the plan covers some regions only)."""
        if self.plan is None:
            return "no plan"
        planned = ~self.unplanned
        if not np.array_equal(positions[planned], self.plan[self.index][planned]):
            return "off plan"
        nxt = self._next_cells()
        moving = planned & (nxt != positions).any(axis=1)
        if (fixed & moving).any():
            return "held"
        if reserved_flat and moving.any():
            flat = nxt[moving, 0] * self.width + nxt[moving, 1]
            if np.isin(flat, list(reserved_flat)).any():
                return "held"
        if self.replan_every and self.index >= self.replan_every:
            return "periodic"
        if self.unplanned.any():
            return "unplanned"
        return ""

    def planning_goals(self, positions) -> np.ndarray:
        """The goals a plan heads for: the robots' goals where they are distinct; where several
        robots share a goal cell (lifelong streams draw goals per robot), the one nearest to it
        keeps it and the others head for the nearest cells no robot heads for (their own goal
        comes back with the next re-plan, after the first one moves on). A robot cut off from
        its goal heads for the nearest such cell it can reach."""
        goals = self.goals
        w = self.width
        flat = (goals[:, 0] * w + goals[:, 1]).tolist()
        now = (np.asarray(positions)[:, 0] * w + np.asarray(positions)[:, 1]).tolist()
        dist = self.planner.distances(flat)
        cut_off = [dist[i][now[i]] < 0 for i in range(len(flat))]
        if len(set(flat)) == len(flat) and not any(cut_off):
            return goals
        nearest = sorted(range(len(flat)), key=lambda i: (cut_off[i], dist[i][now[i]], i))
        used: set[int] = set()
        losers = []
        for i in nearest:
            if flat[i] in used or cut_off[i]:
                losers.append(i)
            else:
                used.add(flat[i])
        out = goals.copy()
        for i in losers:
            d = np.asarray(self.planner.distances([now[i]])[0] if cut_off[i] else dist[i])
            cells = np.flatnonzero(d >= 0)
            for cell in cells[np.argsort(d[cells], kind="stable")].tolist():
                if cell not in used:
                    used.add(cell)
                    out[i] = divmod(cell, w)
                    break
        return out

    def _call_planner(self, positions, goals, rankings, fixed, reserved):
        """LaCAM from `positions`; with `restarts` > 1, that many searches (tie-breaking seeds
        seed, seed + 1, ...) each in the whole budget (`shared_budget`: in what the earlier ones
        left of it), keeping the shortest whole plan (least makespan, then least sum of costs):
        LaCAM's first-found plans vary widely in length (mazes: one seed's plan fits 128 steps
        on 12 of 20 instances, the best of 16 seeds' on 16, docs/results.md)."""
        began = time.perf_counter()
        result, best = None, None
        seed = self.planner.seed
        restarts = self.restarts if self.streamed_restarts or not self.streamed else 1
        # a plan this short ends the restarts (restart_ratio; computed once, only when asked)
        short_enough = (self.restart_ratio * self._longest_distance(positions, goals)
                        if self.restart_ratio > 0 and restarts > 1 else None)
        try:
            for k in range(restarts):
                budget = self.planning_budget
                if self.shared_budget:
                    budget -= time.perf_counter() - began
                    if k and budget <= 0:
                        break
                self.planner.seed = seed + k
                found = self.planner.plan(positions, goals, rankings=rankings,
                                          priorities=self.priorities[self._subset], fixed=fixed,
                                          reserved=reserved, time_limit=max(budget, 0.0),
                                          max_nodes=self.max_nodes)
                if result is None:
                    result = found
                if found.solved:
                    p = found.positions
                    key = (len(p), int((p[1:] != p[-1]).any(axis=2).sum()))
                    if best is None or key < best[0]:
                        best = (key, found)
                    if short_enough is not None and best[0][0] - 1 <= short_enough:
                        break
        finally:
            self.planner.seed = seed
        if best is not None:
            result = best[1]
        spent = time.perf_counter() - began
        c = self.counters
        c["planner_calls"] += 1
        c["planner_seconds"] += spent
        c["planner_max_seconds"] = max(c["planner_max_seconds"], spent)
        return result

    def _longest_distance(self, positions, goals) -> int:
        """The longest of the agents' distances to their goals (a plan's least makespan)."""
        w = self.width
        flat = (np.asarray(goals)[:, 0] * w + np.asarray(goals)[:, 1]).tolist()
        rows = self.planner.distances(flat)
        now = np.asarray(positions)[:, 0] * w + np.asarray(positions)[:, 1]
        return max((int(rows[i][c]) for i, c in enumerate(now.tolist())), default=0)

    def replan(self, positions, rankings=None, fixed=None, reserved=()) -> bool:
        """Plan every agent from `positions` within the budget. Keeps what was found (a whole
        plan, or the plans of the regions that have one) and returns True when every agent
        has a plan."""
        self._subset = slice(None)
        result = self._call_planner(positions, self.planning_goals(positions), rankings, fixed,
                                    reserved)
        if result.solved:
            self._keep(result.positions, np.zeros(self.num_agents, dtype=bool))
            return True
        if result.partial is not None and not result.unsolved.all():
            self._keep(result.partial, result.unsolved)
        else:
            self.plan = None
        self._failed()
        return False

    def _plan_unplanned(self, positions, rankings, fixed, reserved) -> bool:
        """Plan the agents of the regions without a plan, keeping the others' plan."""
        idx = np.flatnonzero(self.unplanned)
        self._subset = idx
        result = self._call_planner(positions[idx], self.planning_goals(positions)[idx],
                                    rankings[idx], fixed[idx], reserved)
        self._subset = slice(None)
        new, still = result.positions, np.zeros(len(idx), dtype=bool)
        if new is None:
            if result.partial is None or result.unsolved.all():
                self._failed()
                return False
            new, still = result.partial, result.unsolved
        old = self.plan[self.index:]
        horizon = max(len(old), len(new))
        merged = np.concatenate([old, np.repeat(old[-1:], horizon - len(old), axis=0)])
        merged[:, idx] = np.concatenate([new, np.repeat(new[-1:], horizon - len(new), axis=0)])
        unplanned = np.zeros(self.num_agents, dtype=bool)
        unplanned[idx[still]] = True
        self._keep(merged, unplanned)
        if still.any():
            self._failed()
            return False
        return True

    def _keep(self, plan, unplanned) -> None:
        self.plan, self.index, self.unplanned = plan, 0, unplanned
        self.counters["plans_found"] += 1
        if not unplanned.any():
            self._retry_interval = 1

    def _failed(self) -> None:
        """No (whole) plan: the next try waits 1, 2, 4, ... ticks (up to `max_retry_interval`),
        so an instance the planner cannot solve does not spend the budget every tick."""
        self._retry_at = self.counters["ticks"] + self._retry_interval
        self._retry_interval = min(2 * self._retry_interval, self.max_retry_interval)

    def step(self, positions, rankings, fixed=None, reserved=()) -> ShieldStep:
        """One tick (arguments as `PIBTShield.step`): the kept plan's next step, a re-planned
        one, or the fallback rule's step over `rankings` for the agents without a plan."""
        began = time.perf_counter()
        positions = self.fallback._check_positions(positions)
        n = self.num_agents
        prefs = validate_rankings(rankings, n)
        fixed = np.zeros(n, dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool).copy()
        if fixed.shape != (n,):
            raise ValueError(f"fixed must have shape ({n},), got {fixed.shape}")
        w = self.width
        now = positions[:, 0] * w + positions[:, 1]
        reserved_flat = set()
        for cell in reserved:
            r, c = int(cell[0]), int(cell[1])
            if 0 <= r < self.height and 0 <= c < w:
                reserved_flat.add(r * w + c)
        if reserved_flat:
            fixed |= np.isin(now, list(reserved_flat))  # standing on a reserved cell: held
        reason = self.why_replan(positions, fixed, reserved_flat)
        c = self.counters
        if reason in ("no plan", "unplanned") and c["ticks"] < self._retry_at:
            reason = ""  # the last try failed: wait for the next one
        if reason == "unplanned":
            self._plan_unplanned(positions, prefs, fixed, reserved)
        elif reason:
            if reason in ("held", "off plan", "periodic"):
                c["repairs_" + reason.replace(" ", "_")] += 1
            old = (self.plan, self.index, self.unplanned)
            if not self.replan(positions, prefs, fixed, reserved) and reason == "periodic":
                self.plan, self.index, self.unplanned = old  # it still holds here: keep it
        if self.plan is None:
            step = self.fallback.step(positions, prefs, fixed=fixed, reserved=reserved)
            c["fallback_ticks"] += 1
            c["fallback_agent_ticks"] += n
        else:
            nxt = self._next_cells().copy()
            self.index = min(self.index + 1, len(self.plan) - 1)
            unplanned = self.unplanned
            if unplanned.any():
                # regions never meet: PIBT's moves for the unplanned regions, the plan's for
                # the rest; priorities advance once, from the cells finally commanded
                saved = self.fallback.priorities.copy()
                pibt = self.fallback.step(positions, prefs, fixed=fixed, reserved=reserved)
                nxt[unplanned] = pibt.positions[unplanned]
                self.fallback.priorities = saved
                self.fallback.tick -= 1
                c["fallback_ticks"] += 1
                c["fallback_agent_ticks"] += int(unplanned.sum())
            else:
                c["planned_ticks"] += 1
            actions = self.fallback._action_of_delta[nxt[:, 0] * w + nxt[:, 1] - now + w]
            overridden = (actions != prefs[:, 0]) & ~fixed
            self.fallback.advance_priorities(nxt)
            self.fallback.tick += 1
            step = ShieldStep(nxt, actions, overridden)
        spent = time.perf_counter() - began
        c["ticks"] += 1
        c["tick_seconds"] += spent
        c["tick_max_seconds"] = max(c["tick_max_seconds"], spent)
        return step


def distance_rankings(keeper_or_shield, positions) -> np.ndarray:
    """(N, 5) every agent's actions by distance to its goal (plain PIBT's ranking, this tick's
    tie-breakers), from a `PIBTShield` or `PlanKeeper`."""
    shield = getattr(keeper_or_shield, "fallback", keeper_or_shield)
    positions = np.asarray(positions, dtype=np.int64)
    flat = positions[:, 0] * shield.width + positions[:, 1]
    return np.stack([shield.anchored_ranking(i, int(flat[i])) for i in range(len(flat))]) \
        if len(flat) else np.zeros((0, NUM_ACTIONS), dtype=np.int64)


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

    def __init__(self, grid, goals, planning_budget: float = 5.0, replan_every: int = 0,
                 max_nodes: int = 1_000_000, seed: int = 0, swap: bool = False,
                 rule: str | None = None, anchor_patience: int | None = None,
                 restarts: int = 1):
        self.keeper = PlanKeeper(grid, goals, planning_budget=planning_budget,
                                 replan_every=replan_every, max_nodes=max_nodes, seed=seed,
                                 swap=swap, restarts=restarts)
        self.rule = None
        if rule is not None:
            from .pibt import PIBT_RULES, rule_options

            if rule not in PIBT_RULES:
                raise ValueError(f"rule must be one of {PIBT_RULES}, got {rule!r}")
            self.rule = PIBTShield(grid, goals, **rule_options(rule),
                                   anchor_patience=anchor_patience)
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
        if np.array_equal(self._rule_step(positions, rankings), keeper._next_cells()):
            self.last["rule_replan"] = False
            return actions
        # the rule would leave the plan: plan again from here with the rule's priorities and
        # its anchored top agent's ranking at the root (the first step the rule would take)
        top = rule.anchored_agent()
        if top >= 0:
            flat = int(positions[top, 0] * keeper.width + positions[top, 1])
            rankings[top] = rule.anchored_ranking(top, flat)
        old = (keeper.plan, keeper.index, keeper.unplanned)
        found = keeper.replan(positions, rankings)
        self.last["rule_replan"] = True
        if not found and keeper.plan is None:
            keeper.plan, keeper.index, keeper.unplanned = old  # keep the labels we had
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
        rule = self.rule
        state = rule.snapshot()
        out = rule.step(positions, rankings).positions
        rule.restore(state)
        return out

    def _moves(self, positions) -> np.ndarray:
        keeper = self.keeper
        positions = keeper.fallback._check_positions(positions)
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
            plan, w = keeper.plan, keeper.width
            expected = min(keeper.index + 1, len(plan) - 1)
            on_plan = (plan[expected] == positions).all(axis=1) & ~keeper.unplanned
            nxt = plan[min(expected + 1, len(plan) - 1)]
            for i in np.flatnonzero(on_plan).tolist():
                first = int(keeper.fallback._action_of_delta[
                    (nxt[i, 0] - positions[i, 0]) * w + nxt[i, 1] - positions[i, 1] + w])
                rankings[i] = [first] + [a for a in rankings[i].tolist() if a != first]
        old = (keeper.plan, keeper.index, keeper.unplanned)
        found = keeper.replan(positions, rankings)
        if not found and periodic:
            keeper.plan, keeper.index, keeper.unplanned = old
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
        nxt = keeper._next_cells().copy()
        if keeper.unplanned.any():
            if rankings is None:
                rankings = distance_rankings(keeper, positions)
            saved = keeper.fallback.priorities.copy()
            pibt = keeper.fallback.step(positions, rankings)
            keeper.fallback.priorities = saved
            nxt[keeper.unplanned] = pibt.positions[keeper.unplanned]
        w = keeper.width
        delta = (nxt[:, 0] - positions[:, 0]) * w + (nxt[:, 1] - positions[:, 1]) + w
        return keeper.fallback._action_of_delta[delta].copy()

    def trajectory(self) -> np.ndarray | None:
        """The kept plan's remaining trajectory (T'+1, N, 2) from the configuration of the last
        `moves` call, or None."""
        return self.keeper.remaining_plan()


__all__ = ["PlanKeeper", "CommittedExpert", "DEFAULT_PLANNING_BUDGET", "distance_rankings"]
