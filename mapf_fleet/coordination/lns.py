"""Windowed PIBT-LNS: a plan over the next ticks, repaired every tick (the `_lns` rules).

PIBT and EPIBT decide one tick from the rankings; a planner that looks several ticks ahead for
all agents together (RHCR, windowed PBS; WPPL, windowed PIBT + LNS, the League of Robot Runners
2023 winner: Jiang et al., "Scaling Lifelong Multi-Agent Path Finding to More Realistic Settings",
SoCS 2024) sees a queue or a head-on meeting before it forms and lets one robot wait or step
aside for another. This rule is WPPL's recipe inside the PIBT rules' shield:

1. **Initial plan.** The rule's own PIBT rolled out `window` ticks on a copy of its state (the
   first tick with the robots' rankings, the next ones with the distance rankings), and the plan
   kept from the last tick shifted by one tick (its robots wait at the end) where every robot
   is where that plan put it: the cheaper of the two.
2. **Repair (LNS).** `iterations` times: a robot drawn in proportion to its delay (its plan's cost
   above its distance to its goal), the robots whose planned cells lie on its shortest way
   (`neighbourhood` robots in all), their paths removed and planned again one by one in a random
   order, each by a space-time A* against the others' paths (`window_search`: no two robots in
   one cell, no two trading cells, no move against a one-way lane); the new paths are kept when
   their cost is lower, else the old ones are put back.
3. **The tick.** Each robot's planned first move ranked first, its own ranking after it, through
   `PIBTShield.step`: every guarantee of the PIBT rules (no vertex or swap conflict, obstacles,
   lanes, fixed robots, reserved cells, the anchor, swap) is the shield's, unchanged. The plan's
   first moves are conflict-free, so the shield executes them except where the anchor or swap
   overrule; then next tick's plan starts from the rollout alone.

**Swap, where the plan is stuck** (the `_swap_lns` rules). The rollout swaps as the rule does; the
executed tick swaps only for a robot that has spent `LNS_SWAP_STALL` ticks off its goal since it
last came closer to it, or with one (ticks on its goal do not count, nor start the count again: two
robots whose goals lie in one corridor can push each other off them in turn for ever, each on its
goal every few ticks). A swap the plan did not make overrules its first moves, and in continuous
operation that cost throughput (inside POGEMA, lifelong, 32 agents: the plan executed without
swap moved 2-3 % more goals a step); without any swap in the executed tick, one-shot crowds in
corridors stay stuck (the paper's 40x40 instances, 64 agents: 0.95 solved against 1.00), which
is where robots stall (docs/results.md, "A windowed plan repaired every tick").

A path's cost (WPPL's objective): its step costs over the window (1 a move or a wait, or the
guidance graph's costs; waiting on the goal is free) plus the distance to the goal from where it
ends. The anchored robot and held robots (fixed, or on a reserved cell) keep the initial plan's
path (the repairs plan the others around them).
Randomness: a generator seeded by the tick, so a run is reproducible.
"""

from __future__ import annotations

import heapq

import numpy as np
from numba import njit

from mapf_fleet.grid.actions import NUM_ACTIONS, STAY

from .pibt import PIBTShield, ShieldStep
from .ranking import validate_rankings
from . import rules


def window_search(start, goal, dist, targets, costs, occ, window, work=None):
    """(path (window + 1,) flat cells, cost): the cheapest path of `window` moves from `start`
    that meets no path in `occ` ((window + 1, cells) int32: the agent at each cell at each
    step, -1 free, -2 reserved), cost = step costs (`costs` (cells, 5); waiting on `goal` is
    free) + `dist` from its last cell; path[0] = -1 and cost inf when there is none.
    work: a `SearchWork` reused between searches (None: one of its own)."""
    if work is None:
        work = SearchWork((window + 1) * targets.shape[0])
    work.mark += 1
    if work.mark >= 2**31 - 1:  # the stamps wrap: start them afresh
        work.seen[:] = 0
        work.done[:] = 0
        work.mark = 1
    return _window_search(int(start), int(goal), dist, targets, costs, occ, int(window), work.g,
                          work.parent, work.seen, work.done, work.mark)


class SearchWork:
    """A space-time search's arrays, allocated once for (window + 1) x cells states: a state's
    entries count only where its stamp is the current search's (no clearing between searches:
    on a 128x128 map clearing them cost more than the search)."""

    def __init__(self, states: int):
        self.g = np.empty(states, dtype=np.float64)
        self.parent = np.empty(states, dtype=np.int64)
        self.seen = np.zeros(states, dtype=np.int32)
        self.done = np.zeros(states, dtype=np.int32)
        self.mark = 0


@njit(cache=True, nogil=True)
def _window_search(start, goal, dist, targets, costs, occ, window, g, parent, seen, done,
                   mark):  # pragma: no cover (compiled)
    """`window_search`'s loop; g / parent count where seen == mark, closed where done == mark."""
    cells = targets.shape[0]
    path = np.full(window + 1, -1, np.int64)
    g[start] = 0.0
    seen[start] = mark
    heap = [(float(dist[start]), 0.0, start)]  # BFS steps are integers, guided costs floats
    while heap:
        _, _, s = heapq.heappop(heap)
        if done[s] == mark:
            continue
        done[s] = mark
        t = s // cells
        u = s - t * cells
        if t == window:
            k = s
            for tt in range(window, -1, -1):
                path[tt] = k - tt * cells
                k = parent[k]
            return path, g[s] + dist[u]
        for a in range(targets.shape[1]):
            v = targets[u, a]
            if v < 0 or occ[t + 1, v] != -1:
                continue
            if v != u:
                j = occ[t + 1, u]
                if j >= 0 and occ[t, v] == j:
                    continue  # j comes the other way: a swap
            ng = g[s] + (0.0 if (v == u and u == goal) else costs[u, a])
            ns = (t + 1) * cells + v
            if seen[ns] != mark or ng < g[ns]:
                seen[ns] = mark
                g[ns] = ng
                parent[ns] = s
                heapq.heappush(heap, (ng + dist[v], -float(t + 1), ns))  # deeper first on ties
    return path, np.inf


class LNSShield(PIBTShield):
    """`PIBTShield` whose rankings are reordered by a windowed plan repaired by LNS (module
    docstring). Arguments as `PIBTShield` (hindrance refused) plus `window` (ticks planned),
    `iterations` (repairs a tick) and `neighbourhood` (robots a repair re-plans)."""

    def __init__(self, grid, goals, anchor: bool = False, swap: bool = False,
                 hindrance: bool = False, patient: bool = False,
                 anchor_patience: int | None = None, guidance=None, window: int | None = None,
                 iterations: int | None = None, neighbourhood: int | None = None):
        # None: the rules' constants, read from `rules` now (not bound at import: one place to
        # change them, in a process or a test)
        window = rules.LNS_WINDOW if window is None else window
        iterations = rules.LNS_ITERATIONS if iterations is None else iterations
        neighbourhood = rules.LNS_NEIGHBOURHOOD if neighbourhood is None else neighbourhood
        if hindrance:
            raise ValueError("LNS does not combine with hindrance (both order the first moves)")
        super().__init__(grid, goals, anchor=anchor, swap=swap, hindrance=False, patient=patient,
                         anchor_patience=anchor_patience, guidance=guidance)
        for name, value, least in (("window", window, 1), ("iterations", iterations, 0),
                                   ("neighbourhood", neighbourhood, 1)):
            if int(value) < least:
                raise ValueError(f"the LNS {name} must be >= {least}, got {value!r}")
        self.window, self.iterations = int(window), int(iterations)
        self.neighbourhood = int(neighbourhood)
        self._plan: np.ndarray | None = None  # (N, window + 1) flat cells, kept between ticks
        self.improved = 0  # repairs kept in the last tick
        self._work: SearchWork | None = None
        # per agent: its least distance to its goal so far and the ticks it has spent off its
        # goal since it got closer (a new goal starts it afresh): who the executed tick may swap
        self._closest = np.full(self.num_agents, np.inf)
        self._since_closer = np.zeros(self.num_agents, dtype=np.int64)
        self._stuck: np.ndarray | None = None  # set during the executed tick only

    # --- state ----------------------------------------------------------------------------------
    def set_guidance(self, guidance) -> None:
        super().set_guidance(guidance)
        self._plan = None  # its moves may cross a new lane
        self._closest[:], self._since_closer[:] = np.inf, 0  # distances changed scale

    def reset(self) -> None:
        super().reset()
        self._plan = None
        self._closest[:], self._since_closer[:] = np.inf, 0

    def set_goals(self, goals) -> np.ndarray:
        changed = super().set_goals(goals)
        self._closest[changed], self._since_closer[changed] = np.inf, 0
        return changed

    def snapshot(self) -> dict:
        state = super().snapshot()
        state["plan"] = None if self._plan is None else self._plan.copy()
        state["closest"], state["since_closer"] = self._closest.copy(), self._since_closer.copy()
        return state

    def restore(self, state: dict) -> None:
        super().restore(state)
        plan = state.get("plan")
        self._plan = None if plan is None else np.array(plan, dtype=np.int64)
        if "closest" in state:
            self._closest = np.array(state["closest"], dtype=np.float64)
            self._since_closer = np.array(state["since_closer"], dtype=np.int64)

    # --- the tick -------------------------------------------------------------------------------
    def step(self, positions, rankings, fixed=None, reserved=()) -> ShieldStep:
        positions = self.check_positions(positions)
        asked = validate_rankings(rankings, self.num_agents)
        fixed = self.check_fixed(fixed)
        paths, held, rows = self._planned(positions, asked, fixed, reserved)
        first = self._action_of_delta[paths[:, 1] - paths[:, 0] + self.width]
        self._stuck = self._stalled(paths[:, 0], rows) >= rules.LNS_SWAP_STALL if self.swap else None
        try:
            result = self.step_first(positions, asked, first, fixed, reserved, held)
        finally:
            self._stuck = None
        self._plan = paths
        return result

    def _stalled(self, flat, rows) -> np.ndarray:
        """(N,) ticks each agent has spent off its goal since it last came closer to it, this
        tick counted (reaching its goal the first time is coming closer; a tick on it adds
        nothing); `rows`: the tick's `_agent_rows`."""
        dist = np.fromiter((row[c] for row, c in zip(rows, flat.tolist())),
                           dtype=np.float64, count=len(flat))
        closer = dist < self._closest
        self._since_closer = np.where(closer, 0, self._since_closer + (dist > 0))
        self._closest = np.minimum(self._closest, dist)
        return self._since_closer

    def _swap_partner(self, i: int, target: int, current, occupied_now, decided) -> int:
        """The rule's swap in the rollout; in the executed tick only for or with a stuck
        agent (module docstring)."""
        j = super()._swap_partner(i, target, current, occupied_now, decided)
        if j >= 0 and self._stuck is not None and not (self._stuck[i] or self._stuck[j]):
            return -1
        return j

    def plan(self, positions, rankings, fixed=None, reserved=()) -> np.ndarray:
        """(N, window + 1) flat cells: the repaired plan, each agent's cell now first (the state
        is not advanced; `step` runs this and executes the first moves)."""
        positions = self.check_positions(positions)
        asked = validate_rankings(rankings, self.num_agents)
        return self._planned(positions, asked, self.check_fixed(fixed), reserved)[0]

    def _planned(self, positions, asked, fixed, reserved):
        """(the repaired plan, the held agents, each agent's distance row)."""
        rows = self._agent_rows()
        held = fixed.copy()
        flat = positions[:, 0] * self.width + positions[:, 1]
        occupant = {c: i for i, c in enumerate(flat.tolist())}
        holders, blocked = self.split_reserved(reserved, occupant)
        held[holders] = True
        paths = self._rollout(positions, asked, fixed, reserved, rows)
        costs = self._costs(paths, rows)
        kept = self._shifted(flat, held, blocked)
        if kept is not None:
            kept_costs = self._costs(kept, rows)
            if kept_costs.sum() < costs.sum():
                paths, costs = kept, kept_costs
        top = self.anchored_agent(fixed)
        movable = ~held
        if top >= 0:
            movable[top] = False
        self._repair(paths, costs, rows, movable, blocked)
        return paths, held, rows

    # --- 1. the initial plan --------------------------------------------------------------------
    def _rollout(self, positions, asked, fixed, reserved, rows) -> np.ndarray:
        """The rule's PIBT over `window` ticks on a copy of its state."""
        n, w = self.num_agents, self.width
        paths = np.empty((n, self.window + 1), dtype=np.int64)
        paths[:, 0] = positions[:, 0] * w + positions[:, 1]
        state = self.snapshot()
        try:
            pos, ranks = positions, asked
            for t in range(1, self.window + 1):
                pos = PIBTShield.step(self, pos, ranks, fixed=fixed, reserved=reserved).positions
                paths[:, t] = pos[:, 0] * w + pos[:, 1]
                if t < self.window:
                    ranks = self.distance_rankings(paths[:, t], rows=rows)
        finally:
            self.restore(state)
        return paths

    def _shifted(self, flat, held, blocked) -> np.ndarray | None:
        """The last tick's plan one tick on (waiting at its end), or None where a robot is not
        where it put it, a held robot would move or a reserved cell would be entered."""
        plan = self._plan
        if plan is None or plan.shape != (self.num_agents, self.window + 1) \
                or not np.array_equal(plan[:, 1], flat):
            return None
        kept = np.concatenate([plan[:, 1:], plan[:, -1:]], axis=1)
        if (kept[held] != kept[held, :1]).any() or np.isin(kept[:, 1:], blocked).any():
            return None
        return kept

    def _agent_rows(self) -> list[np.ndarray]:
        """Per agent its goal's distances (unreachable above any path): views of the map's shared
        table (`_distance_list`), no copies (float64 copies of every goal's row would cost 8
        bytes a cell a robot: 21 GB at 10,000 robots on 512x512)."""
        return [np.asarray(self._distance_list(i)) for i in range(self.num_agents)]

    def _unit_costs(self) -> np.ndarray:
        if self._step_costs is not None:
            return self._step_costs
        return np.ones((self.height * self.width, NUM_ACTIONS))

    def _costs(self, paths, rows) -> np.ndarray:
        """(N,) each path's cost (module docstring)."""
        n, w = len(paths), self.width
        moves = self._action_of_delta[paths[:, 1:] - paths[:, :-1] + w]
        steps = self._unit_costs()[paths[:, :-1], moves]
        goals = np.asarray(self._goal_flat, dtype=np.int64)[:, None]
        steps = np.where((moves == STAY) & (paths[:, :-1] == goals), 0.0, steps)
        end = np.array([rows[i][paths[i, -1]] for i in range(n)], dtype=np.float64)
        return steps.sum(axis=1) + end

    # --- 2. the repair --------------------------------------------------------------------------
    def _repair(self, paths, costs, rows, movable, blocked) -> None:
        """LNS over `paths` (N, window + 1), in place; `costs` (N,) follows."""
        n, h = self.num_agents, self.window
        self.improved = 0
        if self.iterations == 0 or not movable.any():
            return
        cells = self.height * self.width
        occ = np.full((h + 1, cells), -1, dtype=np.int32)
        steps = np.arange(h + 1)
        for i in range(n):
            occ[steps, paths[i]] = i
        if blocked:
            occ[1:, blocked] = -2
        unit = self._unit_costs()
        goal_flat = self._goal_flat
        if self._work is None or len(self._work.g) != (h + 1) * cells:
            self._work = SearchWork((h + 1) * cells)
        work = self._work
        starts = paths[:, 0]
        ideal = np.array([rows[i][starts[i]] for i in range(n)])
        rng = np.random.default_rng(self.tick)
        for _ in range(self.iterations):
            with np.errstate(invalid="ignore"):  # a goal out of reach: inf - inf, no delay
                delay = np.where(movable & np.isfinite(costs), costs - ideal, 0.0)
            delay = np.maximum(np.nan_to_num(delay, posinf=0.0), 0.0)
            total = delay.sum()
            if total <= 1e-9:
                return  # every movable robot on its best path
            seed = int(rng.choice(n, p=delay / total))
            group = self._group(seed, paths, occ, rows, movable)
            rng.shuffle(group)
            old, old_costs = paths[group].copy(), costs[group].copy()
            for i in group:
                occ[steps, paths[i]] = -1
            new_cost, written = 0.0, []
            for i in group:
                path, cost = window_search(starts[i], goal_flat[i], rows[i], self._targets,
                                           unit, occ, h, work)
                if path[0] < 0:
                    break
                occ[steps, path] = i
                written.append((i, path, cost))
                new_cost += cost
            if len(written) == len(group) and new_cost < old_costs.sum() - 1e-9:
                for i, path, cost in written:
                    paths[i], costs[i] = path, cost
                self.improved += 1
                continue
            for _, path, _ in written:  # put the old paths back
                occ[steps, path] = -1
            for k, i in enumerate(group):
                occ[steps, old[k]] = i

    def _group(self, seed, paths, occ, rows, movable) -> list[int]:
        """`seed` and up to `neighbourhood - 1` movable robots whose planned cells lie on its
        shortest way (the cells of steepest descent of its distances over the window), the
        nearest robots after them."""
        row, cell = rows[seed], int(paths[seed, 0])
        way = [cell]
        for _ in range(self.window):
            nxt = [c for c in self._targets[cell, 1:].tolist() if c >= 0]
            if not nxt:
                break
            cell = min(nxt, key=row.__getitem__)
            if row[cell] >= row[way[-1]]:
                break
            way.append(cell)
        found = occ[:, way].T.ravel()  # along the way, each cell's occupants in time order
        group = [seed]
        for j in found.tolist():
            if j >= 0 and j not in group and movable[j]:
                group.append(j)
                if len(group) == self.neighbourhood:
                    return group
        start = paths[:, 0]
        r, c = np.divmod(start, self.width)
        r0, c0 = divmod(int(start[seed]), self.width)
        near = np.argsort(np.abs(r - r0) + np.abs(c - c0), kind="stable").tolist()
        for j in near:
            if j not in group and movable[j]:
                group.append(j)
                if len(group) == self.neighbourhood:
                    break
        return group


__all__ = ["LNSShield", "SearchWork", "window_search"]
