"""The plan keeper: a committed joint plan executed tick by tick (the `lacam` conflict rule).

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

Options: one `PlanOptions` value (budget, re-planning, restarts, fallback rule), with two named
presets: `ARBITER`, the `lacam` conflict rule's, and `EXPERT`, DAgger's committed expert's
(`training.dagger.expert`, which drives a keeper through its public surface: `next_cells`,
`saved` / `restore`, `replan`, `fallback.peek`).

numpy only, as `pibt`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields, replace

import numpy as np

from mapf_fleet.grid.actions import actions_between

from .lacam import LaCAM
from .pibt import PIBTShield, ShieldStep
from .ranking import validate_rankings
from .rules import Rule

# The planning arbiter's default per-tick planning budget (seconds of wall clock)
DEFAULT_PLANNING_BUDGET = 1.0


@dataclass(frozen=True)
class PlanOptions:
    """How a `PlanKeeper` plans: one value, checked once here.

    planning_budget: wall-clock seconds per re-plan. replan_every: re-plan every k ticks even
    when the plan holds (0: only when it breaks). max_nodes: LaCAM's node budget per call.
    seed: LaCAM's tie-breaking seed. max_retry_interval: the longest wait (ticks) between tries
    after failed calls (1, 2, 4, ... up to it). swap: LaCAM's successors by PIBT with swap.
    restarts: LaCAM searches per re-plan, the shortest plan kept. shared_budget: the restarts
    share one `planning_budget` (a re-plan costs at most about the budget) instead of one each.
    restart_ratio: restart only while the shortest plan so far is longer than this many times
    the longest agent's distance to its goal (0: always). streamed_restarts: restart also once
    the goals have changed (a lifelong stream). fallback_rule: the anchored PIBT rule of the
    ticks without a plan (the anchor is what makes the fallback reach every goal)."""

    planning_budget: float = DEFAULT_PLANNING_BUDGET
    replan_every: int = 0
    max_nodes: int = 1_000_000
    seed: int = 0
    max_retry_interval: int = 16
    swap: bool = False
    restarts: int = 1
    shared_budget: bool = False
    restart_ratio: float = 0.0
    streamed_restarts: bool = True
    fallback_rule: str = "pibt_anchor"

    def __post_init__(self):
        if not self.planning_budget > 0:
            raise ValueError(f"planning_budget must be a positive number of seconds, got "
                             f"{self.planning_budget!r}")
        for name, least in (("replan_every", 0), ("max_retry_interval", 1), ("restarts", 1)):
            if int(getattr(self, name)) < least:
                raise ValueError(f"{name} must be >= {least}, got {getattr(self, name)!r}")
        if not float(self.restart_ratio) >= 0:
            raise ValueError(f"restart_ratio must be >= 0, got {self.restart_ratio!r}")
        fallback = Rule.parse(self.fallback_rule, "fallback_rule")
        if not (fallback.is_pibt and fallback.anchor):
            raise ValueError(f"fallback_rule must be an anchored PIBT rule, got "
                             f"{self.fallback_rule!r}")

    def but(self, **changes) -> "PlanOptions":
        """These options with `changes` (None values ignored), checked again."""
        changes = {k: v for k, v in changes.items() if v is not None}
        unknown = set(changes) - {f.name for f in fields(self)}
        if unknown:
            raise TypeError(f"unknown plan option(s) {sorted(unknown)}")
        return replace(self, **changes) if changes else self


# The `lacam` conflict rule (the planning arbiter): successors by PIBT with swap, as the fleet's
# rule; the shortest of 8 searches' plans within the one budget where the first is over 1.5 times
# the longest agent's distance (a first-found plan can miss a step limit where another seed's
# fits), and not once the goals stream in (there restarts cost several times the tick time for
# nothing); its fallback step is the fleet's rule (docs/results.md, "The planning arbiter")
ARBITER = PlanOptions(swap=True, restarts=8, shared_budget=True, restart_ratio=1.5,
                      streamed_restarts=False, fallback_rule="pibt_anchor_swap")
# DAgger's committed expert: a longer budget per plan (labels are made offline, a node budget
# bounds them)
EXPERT = PlanOptions(planning_budget=5.0)


class PlanKeeper:
    """The `lacam` conflict rule: the interface of `PIBTShield` (`step`, `set_goals`, `reset`,
    `advance_priorities`, `goals`, `priorities`, `base_priority`, `tick`) over a kept LaCAM plan.

    grid: (H, W), nonzero = obstacle. goals: (N, 2). options: a `PlanOptions` (default: its
    defaults; `ARBITER` for the `lacam` rule); keyword `changes` override single options
    (`PlanKeeper(grid, goals, ARBITER, planning_budget=0.5)`). guidance: a
    `grid.guidance.Guidance` for the map, read by the planner and the fallback rule alike."""

    def __init__(self, grid, goals, options: PlanOptions | None = None, guidance=None,
                 **changes):
        options = (options or PlanOptions()).but(**changes)
        self.options = options
        self.fallback = PIBTShield(grid, goals, **Rule.parse(options.fallback_rule).pibt_options(),
                                   guidance=guidance)
        self.grid = self.fallback.grid
        self.height, self.width = self.grid.shape
        self.num_agents = self.fallback.num_agents
        self.planner = LaCAM(self.grid, seed=options.seed, swap=options.swap, guidance=guidance)
        self.planning_budget = float(options.planning_budget)
        self.replan_every = int(options.replan_every)
        self.max_nodes = int(options.max_nodes)
        self.restarts = int(options.restarts)
        self.shared_budget = bool(options.shared_budget)
        self.restart_ratio = float(options.restart_ratio)
        self.streamed_restarts = bool(options.streamed_restarts)
        self.max_retry_interval = int(options.max_retry_interval)
        self.streamed = False  # the goals changed since the episode began
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

    def set_guidance(self, guidance) -> None:
        """A new guidance graph for the fallback and the next re-plans; the kept plan stays (it
        is still valid: guidance only changes which plan is preferred)."""
        self.fallback.set_guidance(guidance)
        options = self.options
        self.planner = LaCAM(self.grid, seed=options.seed, swap=options.swap, guidance=guidance)

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

    def next_cells(self) -> np.ndarray:
        """The kept plan's next configuration (N, 2) (the current one at its end)."""
        plan = self.plan
        return plan[min(self.index + 1, len(plan) - 1)]

    def saved(self) -> tuple:
        """The kept plan and where the robots are on it, for `restore`: a caller that tries a
        re-plan and keeps the old plan when it fails."""
        return self.plan, self.index, self.unplanned

    def restore(self, saved: tuple) -> None:
        self.plan, self.index, self.unplanned = saved

    def why_replan(self, positions, fixed, reserved_flat) -> str:
        """"" when the kept plan holds for this state, else the reason to plan: "no plan",
        "off plan", "held", "periodic", or "unplanned" (the plan covers some regions only)."""
        if self.plan is None:
            return "no plan"
        planned = ~self.unplanned
        if not np.array_equal(positions[planned], self.plan[self.index][planned]):
            return "off plan"
        nxt = self.next_cells()
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
        far = self.planner.table.unreachable
        cut_off = [dist[i][now[i]] >= far for i in range(len(flat))]
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
            # the table's own row, no -1 copy (a guided copy is float64, a new goal's cost twice)
            d = self.planner.table.whole(now[i] if cut_off[i] else flat[i])
            cells = np.flatnonzero(d < far)
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
        LaCAM's first-found plans vary widely in length, most of all in mazes, so another seed's
        plan may fit a step limit the first one misses (docs/results.md, "The expert ceiling,
        second reading", item 5)."""
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

    def _longest_distance(self, positions, goals) -> float:
        """The longest of the agents' distances to their goals (a plan's least makespan)."""
        w = self.width
        flat = (np.asarray(goals)[:, 0] * w + np.asarray(goals)[:, 1]).tolist()
        rows = self.planner.distances(flat)
        now = np.asarray(positions)[:, 0] * w + np.asarray(positions)[:, 1]
        return max((rows[i][c] for i, c in enumerate(now.tolist())), default=0)

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
        positions = self.fallback.check_positions(positions)
        n = self.num_agents
        prefs = validate_rankings(rankings, n)
        fixed = self.fallback.check_fixed(fixed)
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
            old = self.saved()
            if not self.replan(positions, prefs, fixed, reserved) and reason == "periodic":
                self.restore(old)  # it still holds here: keep it
        if self.plan is None:
            step = self.fallback.step(positions, prefs, fixed=fixed, reserved=reserved)
            c["fallback_ticks"] += 1
            c["fallback_agent_ticks"] += n
        else:
            nxt = self.next_cells().copy()
            self.index = min(self.index + 1, len(self.plan) - 1)
            unplanned = self.unplanned
            if unplanned.any():
                # regions never meet: PIBT's moves for the unplanned regions, the plan's for
                # the rest; priorities advance once, from the cells finally commanded
                pibt = self.fallback.peek(positions, prefs, fixed=fixed, reserved=reserved)
                nxt[unplanned] = pibt.positions[unplanned]
                c["fallback_ticks"] += 1
                c["fallback_agent_ticks"] += int(unplanned.sum())
            else:
                c["planned_ticks"] += 1
            actions = actions_between(positions, nxt)
            overridden = (actions != prefs[:, 0]) & ~fixed
            self.fallback.advance(nxt)
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
    return shield.distance_rankings(flat)


__all__ = ["PlanKeeper", "PlanOptions", "ARBITER", "EXPERT", "DEFAULT_PLANNING_BUDGET",
           "distance_rankings"]
