"""EPIBT: PIBT over short multi-step operations, a longer horizon per tick (the `_epibt` rules).

PIBT decides one step: an agent takes the closest free cell and can walk into a place from which
the next step is blocked (two agents that meet head-on one cell later, a queue that stops). EPIBT
(Yukhnevich & Andreychuk, "Enhancing PIBT via Multi-Action Operations", 2025; the League of Robot
Runners 2024 winners' planner) lets each agent choose an *operation*, a sequence of `horizon`
moves, in priority order: an operation must not meet any operation already chosen at any step of
the horizon (no two agents in one cell, no two trading cells), and an agent still undecided whose
cell the operation enters inherits the priority and must choose first (PIBT's push), with
backtracking to the next operation when it cannot. Only the first move of each operation is
executed; the next tick plans afresh (nothing is kept between ticks).

Operations: every sequence of `horizon` actions whose cells, waits aside, are all different (no
step back onto a cell just left: that is a wait with extra moves), `operations(horizon)`; 85 at
horizon 3. An agent ranks its operations by their cost to its goal (the step costs along the
operation plus the distance from where it ends: BFS steps, or guided costs and step costs under
the shield's guidance graph), equal costs by its own ranking of the first move (the learned
policy's order, or the distance ranking's per-tick tie-break), then by the distances along the
way (closer earlier first). The anchored top agent (rules with an anchor) ranks its operations
by its anchored first-move order first, so the plan starts with the move the anchor will take.

Safety by construction: the tick itself is `PIBTShield.step` with each agent's EPIBT first move
ranked first and its own ranking after it (where the operation starts by waiting, the agent's own
ranking stands: a wait at the first step is mostly an operation that found no move free over the
whole horizon, and PIBT's one-step push and swap still get the agent through there). Every
guarantee of the PIBT rules (no vertex or swap conflict, one cell per tick, obstacles, fixed
agents, reserved cells, the anchor, swap, the patient anchor's clock) is the shield's, unchanged;
EPIBT only reorders the rankings. First moves of one EPIBT plan are conflict-free at step 1, so
the shield executes them as planned except where the anchor or swap overrule them (then the
shield's own pushes decide, safely).

Cost bound: the search stops pushing once it has taken `TRIES_PER_AGENT` operations that push,
per agent, in the tick; agents planned after that take the first operation that needs no push
(waiting in place always qualifies: no chosen operation enters the cell of an agent not yet
decided).

Hindrance is not combined with EPIBT: it reorders equally short first moves by the neighbours
they block, which is what the horizon decides here (the two would overrule each other).
"""

from __future__ import annotations

from itertools import product

import numpy as np

from mapf_fleet.grid.actions import ACTION_DELTAS, NUM_ACTIONS, STAY

from .pibt import PIBTShield, ShieldStep
from .ranking import validate_rankings
from .rules import EPIBT_HORIZON  # the default horizon, and why, where the rule names live

# Operations that push others, taken per agent per tick on average, before the search stops
# pushing: bounds the backtracking (PIBT's push over operations can branch at every step of
# every operation). 8: in jams a larger bound bought no throughput and cost 4x the tick
# (docs/results.md, "A longer horizon per tick (EPIBT)").
TRIES_PER_AGENT = 8
_HEAD = 4  # operations of an agent turned into Python lists first (`_search.candidates`)
_OPERATIONS: dict[int, np.ndarray] = {}


def operations(horizon: int = EPIBT_HORIZON) -> np.ndarray:
    """(K, horizon) int64: the operations, action sequences (DHC order) whose cells, waits
    aside, are all different; all waits first."""
    horizon = int(horizon)
    if horizon < 1:
        raise ValueError(f"the EPIBT horizon must be >= 1 moves, got {horizon}")
    found = _OPERATIONS.get(horizon)
    if found is None:
        kept = []
        for seq in product(range(NUM_ACTIONS), repeat=horizon):
            cell, seen = (0, 0), {(0, 0)}
            for a in seq:
                if a == STAY:
                    continue
                cell = (cell[0] + int(ACTION_DELTAS[a, 0]), cell[1] + int(ACTION_DELTAS[a, 1]))
                if cell in seen:
                    break
                seen.add(cell)
            else:
                kept.append(seq)
        found = np.array(kept, dtype=np.int64)  # product order: (STAY,) * horizon first
        found.setflags(write=False)
        _OPERATIONS[horizon] = found
    return found


class EPIBTShield(PIBTShield):
    """`PIBTShield` whose rankings are reordered by EPIBT's operations (module docstring).

    Arguments as `PIBTShield` (hindrance refused) plus `horizon`, the moves per operation
    (`EPIBT_HORIZON`). `plan(positions, rankings, fixed, reserved)` gives the operations alone;
    `step` executes their first moves through `PIBTShield.step`."""

    def __init__(self, grid, goals, anchor: bool = False, swap: bool = False,
                 hindrance: bool = False, patient: bool = False,
                 anchor_patience: int | None = None, guidance=None,
                 horizon: int = EPIBT_HORIZON):
        if hindrance:
            raise ValueError("EPIBT does not combine with hindrance (both order the first moves)")
        super().__init__(grid, goals, anchor=anchor, swap=swap, hindrance=False, patient=patient,
                         anchor_patience=anchor_patience, guidance=guidance)
        self.horizon = int(horizon)
        self.ops = operations(self.horizon)
        self.tries = 0  # operations that pushed, taken in the last plan (the cost bound's count)

    # --- the tick -------------------------------------------------------------------------------
    def step(self, positions, rankings, fixed=None, reserved=()) -> ShieldStep:
        positions = self.check_positions(positions)
        asked = validate_rankings(rankings, self.num_agents)
        fixed = self.check_fixed(fixed)
        first, held = self._first_moves(positions, asked, fixed, reserved)
        # the EPIBT move first, then the agent's own ranking without it
        return self.step_first(positions, asked, first, fixed, reserved, held)

    def plan(self, positions, rankings, fixed=None, reserved=()) -> np.ndarray:
        """(N, horizon + 1) flat cells: each agent's chosen operation, its cell now first (the
        state is not advanced; `step` runs this and executes the first moves)."""
        positions = self.check_positions(positions)
        n = self.num_agents
        asked = validate_rankings(rankings, n)
        fixed = np.zeros(n, dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool)
        return self._search(positions, asked, fixed, reserved)[0]

    def _first_moves(self, positions, asked, fixed, reserved):
        """((N,) the action each agent's ranking puts first: its operation's first move, or its
        own first choice where the operation starts by waiting; (N,) held agents)."""
        paths, held = self._search(positions, asked, fixed, reserved)
        first = self._action_of_delta[paths[:, 1] - paths[:, 0] + self.width]
        # a wait is left to PIBT's own step: an operation that starts by waiting is mostly one
        # that found no move free over the whole horizon, where PIBT's push and swap still get
        # the agent through at one step (promoting the wait cost throughput, docs/results.md)
        return np.where(first == STAY, asked[:, 0], first), held

    # --- ranking the operations -----------------------------------------------------------------
    def _ranked_operations(self, current: np.ndarray, asked: np.ndarray, top: int):
        """(paths (N, K, horizon + 1) flat cells, -1 past an invalid move; order (N, K) each
        agent's operations best first; count (N,) of valid ones)."""
        n, ops, h = len(current), self.ops, self.horizon
        k = len(ops)
        paths = np.empty((n, k, h + 1), dtype=np.int64)
        paths[:, :, 0] = current[:, None]
        valid = np.ones((n, k), dtype=bool)
        cost = np.zeros((n, k), dtype=np.float64)
        for t in range(h):
            prev = paths[:, :, t]
            nxt = self._targets[prev, ops[None, :, t]]
            valid &= nxt >= 0
            if self._step_costs is not None:
                cost += self._step_costs[prev, ops[None, :, t]]
            paths[:, :, t + 1] = np.where(valid, nxt, prev)
        if self._step_costs is None:
            cost[:] = h
        # distances along the way: per agent its goal's row (shared table, searched once a goal;
        # a view, unreachable cells already above any path)
        along = np.empty((n, k, h), dtype=np.float64)
        for i in range(n):
            along[i] = np.asarray(self._distance_list(i))[paths[i, :, 1:]]
        cost += along[:, :, -1]
        cost = np.where(valid, np.round(cost, 9), np.inf)
        rank_of = np.empty((n, NUM_ACTIONS), dtype=np.int64)
        rank_of[np.arange(n)[:, None], asked] = np.arange(NUM_ACTIONS)
        first_rank = rank_of[:, ops[:, 0]]
        progress = along.sum(axis=2)
        order = np.lexsort((progress, first_rank, cost), axis=-1)
        if top >= 0:  # the anchored agent: its anchored first-move order before the cost
            order[top] = np.lexsort((progress[top], cost[top], first_rank[top]))
        return paths, order, valid.sum(axis=1)

    # --- the search -----------------------------------------------------------------------------
    def _search(self, positions, asked, fixed, reserved):
        """(paths (N, horizon + 1), held (N,) bool: fixed or standing on a reserved cell)."""
        n, h, w = self.num_agents, self.horizon, self.width
        current = positions[:, 0] * w + positions[:, 1]
        now = current.tolist()
        occupied_now = {cell: i for i, cell in enumerate(now)}
        if len(occupied_now) != n:
            raise ValueError("two agents share a cell in positions")
        top = self.anchored_agent(fixed)
        if top >= 0:
            asked = asked.copy()
            asked[top] = self.anchored_ranking(top, now[top])
        paths, order, count = self._ranked_operations(current, asked, top)
        held = fixed.copy()
        # occ[t]: {cell: agent} at step t of the chosen operations (-2: a reserved cell)
        occ: list[dict[int, int]] = [dict() for _ in range(h + 1)]
        holders, kept_free = self.split_reserved(reserved, occupied_now)
        held[holders] = True
        for cell in kept_free:
            for t in range(1, h + 1):
                occ[t][cell] = -2
        chosen: list[list[int] | None] = [None] * n
        stay = [0] * (h + 1)
        for i in np.flatnonzero(held).tolist():
            chosen[i] = [now[i]] * (h + 1)
            for t in range(1, h + 1):
                occ[t][now[i]] = i
        journal: list[int] = []
        budget = [TRIES_PER_AGENT * max(n, 1)]

        def candidates(i: int):
            # most agents take one of their first operations: convert the rest only if asked
            ranked = order[i, :count[i]]
            yield from paths[i, ranked[:_HEAD]].tolist()
            if len(ranked) > _HEAD:
                yield from paths[i, ranked[_HEAD:]].tolist()

        def assign(i: int, path: list[int]) -> None:
            chosen[i] = path
            for t in range(1, h + 1):
                occ[t][path[t]] = i
            journal.append(i)

        def rollback(mark: int) -> None:
            while len(journal) > mark:
                i = journal.pop()
                path = chosen[i]
                chosen[i] = None
                for t in range(1, h + 1):
                    if occ[t].get(path[t]) == i:
                        del occ[t][path[t]]

        def free(i: int, path: list[int]) -> list[int] | None:
            """The undecided agents `path` would push (in the order it meets them), or None
            when it meets a chosen operation."""
            blockers = []
            for t in range(1, h + 1):
                v, u = path[t], path[t - 1]
                if v in occ[t]:
                    return None  # two agents in one cell at step t
                if u != v:
                    j = occ[t].get(u, -1)
                    if j >= 0 and chosen[j][t - 1] == v:
                        return None  # j comes the other way: a swap
                j = occupied_now.get(v, -1)
                if j >= 0 and j != i and chosen[j] is None and j not in blockers:
                    blockers.append(j)
            return blockers

        def funnel(i: int) -> bool:
            for path in candidates(i):
                blockers = free(i, path)
                if blockers is None:
                    continue
                if blockers:  # a push: counted against the tick's bound
                    if budget[0] <= 0:
                        continue
                    budget[0] -= 1
                mark = len(journal)
                assign(i, path)
                if all(chosen[j] is not None or funnel(j) for j in blockers):
                    return True
                rollback(mark)
            return False

        for i in np.argsort(-self.priorities, kind="stable").tolist():
            if chosen[i] is None and not funnel(i):
                stay[:] = [now[i]] * (h + 1)
                assign(i, list(stay))  # nobody entered its cell: waiting is always possible
        self.tries = TRIES_PER_AGENT * max(n, 1) - budget[0]
        return np.asarray(chosen, dtype=np.int64).reshape(n, h + 1), held


__all__ = ["EPIBTShield", "EPIBT_HORIZON", "TRIES_PER_AGENT", "operations"]
