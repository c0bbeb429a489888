"""PIBT over per-agent rankings: the collision shield under every decentralized policy.

Priority Inheritance with Backtracking (Okumura et al., AIJ 2022) plans one step at a time. Agents
are taken in decreasing priority; each takes the first cell of its ranking that is
free for the next step; when that cell holds an agent that has not decided yet, the occupant
inherits the priority and must move first (recursively); when it cannot, the whole sub-chain is
undone and the next candidate is tried (backtracking). With the five actions ranked by a learned
policy's Q-values this is CS-PIBT (Veerapaneni et al., ICAPS 2024); with actions ranked by the
distance to the goal it is plain PIBT.

Guarantees of `PIBTShield.step`, for any rankings (property-tested): no two agents in
one cell, no two agents trading cells (swap), no agent on an obstacle or off the map, every
agent moves at most one cell. Agents marked `fixed` stay where they are and are never pushed;
`reserved` cells are kept free (a real robot still driving into a cell occupies it).

Dynamic priorities (PIBT's, as pymapf 0.9.0 uses them): agent i starts at i / (N + 1), a
distinct tie-breaker below 1; after each step its priority rises by 1 while it is off its goal
and falls back to i / (N + 1) on its goal. Everything is deterministic for the same inputs.

Anchor (`anchor=True`, off by default): the agent of highest priority ranks its moves by the
distance to its goal (BFS on the map; ties by `ranking.tie_breakers`, as plain PIBT's
rankings), whatever it asked for. PIBT's reachability argument (the top agent takes a shortest-path
step, its priority only rises until it arrives, so every agent in turn reaches its goal) needs
the top agent's ranking to be a distance order; a learned ranking (CS-PIBT) can stall it, which is
where learned rankings lose to plain PIBT in crowds (docs/results.md, "The anchor against plain
PIBT").

Patient anchor (`patient=True`, rule names `pibt_patient...`; `anchor_patience` ticks,
`ANCHOR_PATIENCE` by default): the anchor ranks the top agent by distance only once it has gone
that many ticks without getting closer to its goal than it has been since its goal was set. The
every-tick anchor overrides every wait and detour of the top agent, so a plan (or a policy that
learned one) whose top agent waits for others is knocked off it at every tick: under it, an
expert whose labels the rule executes almost unchanged solved no more dense instances than plain
PIBT (docs/results.md, "The expert ceiling, second reading"). With patience the top agent still
reaches its goal: each `patience + 1` ticks it gets at least one cell closer, so within
(patience + 1) x its distance. Plain PIBT is unchanged by it (its top agent always steps closer,
the clock never runs).

Swap (`swap=True`, off by default; lacam3's PIBT, Okumura, "Engineering LaCAM*", AAMAS 2024,
after "Improving LaCAM", IJCAI 2023): plain PIBT cannot get two agents past each other in a
corridor (the one in front can only be pushed ahead, never through). When an agent's first
candidate cell holds an undecided agent with which it must trade places (walking the corridor
from there with the pusher's distances finds no branch before the pusher's goal, and the other
agent wants the pusher's cell: `swap._swap_required`) and trading is possible (walking back along
the corridor behind the pusher finds a branch cell: `swap._swap_possible`), or, one step ahead, a
neighbour will have to trade with it (the "clear" case), the agent reverses its candidate order
for this tick and, when it gets the first cell of the reversed order, pulls that agent into the
cell it leaves. Over a few ticks the pair backs out to the branch, where the pulled one steps
aside. Combined with a learned ranking: the agent's ranking is its candidate order, and only a
required and possible swap reverses it (the swap test uses BFS distances, the shield's own
maps); the pulled agent's own ranking is not asked (it is marked overridden when the pull is
not its first choice). With the anchor: the top agent's distance order is what swap reverses;
PIBT's reachability argument then no longer holds tick by tick (the top agent may back away
from its goal), which is lacam3's trade: the argument fails in corridors anyway, where swap
gets the pair through.

Hindrance (`hindrance=True`, off by default; Okumura & Nagai, "Lightweight and Effective
Preference Construction in PIBT", SoCS 2025): candidates at equal distance to the agent's goal
are ordered by how many agents standing next to the agent would lose a move that gets them
closer to their own goals if the agent took that cell (a neighbour j counts against cell v when
j is not on v and dist_j(v) < dist_j(j's cell)); fewer first. Which moves the ranking leaves
tied: every maximal run of consecutive candidates in the agent's ranking at the same BFS
distance to its goal (stable: equal hindrance keeps the ranking's order). Under the distance
ranking (plain PIBT, the heuristic, the anchored top agent, `confidence` where the network is
not sure) these runs are exactly the moves the per-tick hash ordered, so it is the paper's
(distance, hindrance, random) order. Under a learned ranking the network's order between moves
at different distances always stands (a choice to wait or detour is kept); only its order
between two equally short moves, adjacent in its ranking, may be overruled in favour of the
one that blocks fewer neighbours. Combined with swap: hindrance orders the candidates first,
swap then reverses that order when a swap is required and possible.

Guarantees, for every combination of anchor, swap and hindrance (each property-tested on random
maps, positions and rankings): no two agents in one cell; no two agents trading cells in one
tick (the swap option trades places over several ticks, never through each other); every agent
moves at most one cell, never onto an obstacle or off the map; a fixed (held) agent stays where
it is and is never pushed nor pulled; reserved cells stay free. (A pull only moves an undecided
agent into the cell the puller leaves, a cell no one else has taken, and the puller never moves
into the pulled agent's cell in the same tick.)

Rule names: `pibt[_anchor|_patient][_swap][_hindrance]`, parsed once by `rules.Rule.parse`;
`Rule.pibt_options()` gives this class's keyword options.

Distances: every distance this rule reads (the anchor's order, swap's corridor walk, hindrance,
the patient anchor's clock) comes from the map's shared `grid.heuristic.DistanceTable`: BFS steps,
or least path costs under a guidance graph (`guidance`). Under guidance the anchored order ranks
a move by its step cost plus the distance from the cell it leads to (Guided PIBT's order; with
unit costs exactly the distance order).

numpy only (no torch, no rclpy): the evaluator, the trainer's actors, the simulator and the
real-robot aggregator all call this one implementation.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mapf_fleet.grid.actions import ACTION_DELTAS, NUM_ACTIONS
from mapf_fleet.grid.heuristic import distance_table

from .push import Push
from .ranking import tie_breakers, validate_rankings
from .rules import ANCHOR_PATIENCE
from .swap import swap_partner

# One recursion level per agent of a push chain; a chain can hold every agent.
_MIN_RECURSION = 10_000
if sys.getrecursionlimit() < _MIN_RECURSION:
    sys.setrecursionlimit(_MIN_RECURSION)


@dataclass(frozen=True)
class ShieldStep:
    """The arbitrated tick: `positions` (N, 2) next cells, `actions` (N,) the executed actions
    (DHC order), `overridden` (N,) bool: the executed action is not the agent's first choice."""

    positions: np.ndarray
    actions: np.ndarray
    overridden: np.ndarray


class PIBTShield:
    """PIBT for one fleet on one map. `step` resolves one tick and advances the priorities.

    grid: (H, W) bool/uint8, nonzero = obstacle. goals: (N, 2) (row, col) cells.
    anchor: the highest-priority agent follows its distance order; swap: lacam3's swap in
    corridors; hindrance: equally short moves ordered by the neighbours they block (module
    docstring). patient: an anchor that waits `ANCHOR_PATIENCE` ticks; anchor_patience: the
    ticks the top agent may go without getting closer to its goal before the anchor ranks it
    (default 0, every tick; `ANCHOR_PATIENCE` when patient). guidance: a
    `grid.guidance.Guidance` for the map (None: BFS steps); every distance comes from the map's
    shared `DistanceTable` under it (`self.distances`).
    """

    def __init__(self, grid, goals, anchor: bool = False, swap: bool = False,
                 hindrance: bool = False, patient: bool = False,
                 anchor_patience: int | None = None, guidance=None):
        grid = np.asarray(grid)
        if grid.ndim != 2:
            raise ValueError(f"grid must be 2-D, got shape {grid.shape}")
        self.grid = grid != 0
        self.height, self.width = self.grid.shape
        goals = np.asarray(goals, dtype=np.int64)
        if goals.ndim != 2 or goals.shape[1] != 2:
            raise ValueError(f"goals must have shape (N, 2), got {goals.shape}")
        self.goals = goals.copy()  # own copy: `set_goals` compares against it
        self._goal_flat = (self.goals[:, 0] * grid.shape[1] + self.goals[:, 1]).tolist()
        self.num_agents = len(goals)
        self._blocked = self.grid.ravel().tolist()
        w = self.width
        # distances per goal CELL (not per agent), shared with every rule, planner and
        # observation on this map: a fleet that hands out new goals at run time reuses a cell's
        # distances whichever agent heads there
        self.distances = distance_table(self.grid, guidance)
        self.distances.reserve(2 * len(goals))  # this tick's goals and the last ones
        self._step_costs = self.distances.step_costs  # None unguided
        # the flat cell each action leads to; -1 off the map, into an obstacle, against a lane
        self._targets = self.distances.move_targets()
        # executed action from the flat displacement (next - current + w)
        self._action_of_delta = np.zeros(2 * w + 1, dtype=np.int64)
        for a in range(1, NUM_ACTIONS):
            self._action_of_delta[ACTION_DELTAS[a, 0] * w + ACTION_DELTAS[a, 1] + w] = a
        self.base_priority = np.arange(self.num_agents, dtype=np.float64) / (self.num_agents + 1)
        self.priorities = self.base_priority.copy()
        self.patient = bool(patient)
        self.anchor = bool(anchor) or self.patient
        if anchor_patience is None:
            anchor_patience = ANCHOR_PATIENCE if self.patient else 0
        if int(anchor_patience) < 0:
            raise ValueError(f"anchor_patience must be >= 0 ticks, got {anchor_patience!r}")
        self.anchor_patience = int(anchor_patience)
        # per agent: its least distance to its goal so far and the ticks since it got there
        # (the patient anchor's clock; a new goal starts it afresh)
        self.best_distance = np.full(self.num_agents, np.inf)
        self.stalled = np.zeros(self.num_agents, dtype=np.int64)
        self.swap = bool(swap)
        self.hindrance = bool(hindrance)
        # valid neighbour cells per flat cell (swap walks corridors, hindrance reads neighbours)
        self._neighbors = [[c for c in row if c >= 0] for row in self._targets[:, 1:].tolist()]
        self.tick = 0  # steps since reset: the anchor's tie-breakers
    def set_guidance(self, guidance) -> None:
        """Read every distance under a new guidance graph from the next step on (online
        guidance: `grid.guidance_made.CongestionFlow`); the patient anchor's clocks start afresh
        (its distances changed scale)."""
        self.distances = distance_table(self.grid, guidance)
        self.distances.reserve(2 * self.num_agents)
        self._step_costs = self.distances.step_costs
        self._targets = self.distances.move_targets()
        self._neighbors = [[c for c in row if c >= 0] for row in self._targets[:, 1:].tolist()]
        self.best_distance[:] = np.inf
        self.stalled[:] = 0

    def reset(self) -> None:
        """Start a new episode: every priority back to its tie-breaker."""
        self.priorities = self.base_priority.copy()
        self.tick = 0
        self.best_distance[:] = np.inf
        self.stalled[:] = 0

    def snapshot(self) -> dict:
        """The state a step depends on besides its inputs (priorities, tick, the patient
        anchor's clocks), copied: `restore` puts it back (an expert asking what the rule would
        do, on a copy of the rule)."""
        return {"priorities": self.priorities.copy(), "tick": self.tick,
                "best_distance": self.best_distance.copy(), "stalled": self.stalled.copy()}

    def restore(self, state: dict) -> None:
        self.priorities = np.asarray(state["priorities"], dtype=np.float64).copy()
        self.tick = int(state["tick"])
        self.best_distance = np.asarray(state["best_distance"], dtype=np.float64).copy()
        self.stalled = np.asarray(state["stalled"], dtype=np.int64).copy()

    def anchored_agent(self, fixed=None) -> int:
        """The agent the anchor ranks by distance at the next step, -1 when none: the one of
        highest priority (not fixed), once it has gone `anchor_patience` ticks without getting
        closer to its goal than before (patience 0: always)."""
        if not self.anchor or not self.num_agents:
            return -1
        top = int(np.argmax(self.priorities))
        if fixed is not None and fixed[top]:
            return -1
        return top if self.stalled[top] >= self.anchor_patience else -1

    def set_goals(self, goals) -> np.ndarray:
        """New goals (N, 2) for the next steps, without rebuilding the shield; returns the bool
        (N,) mask of agents whose goal changed.

        A changed goal puts the agent's priority back to its tie-breaker, as an arrival does:
        PIBT's priority counts the steps an agent has waited for its *current* goal (lifelong
        PIBT's "time since the last goal update"), so a new task starts from the bottom instead
        of inheriting the rank its old task earned; an agent that keeps its goal keeps its
        priority, so the top agent still reaches its goal (the reachability argument)."""
        goals = np.asarray(goals, dtype=np.int64)
        if goals.shape != self.goals.shape:
            raise ValueError(f"goals must have shape {self.goals.shape}, got {goals.shape}")
        changed = (goals != self.goals).any(axis=1)
        if changed.any():
            self.goals = goals.copy()
            self._goal_flat = (self.goals[:, 0] * self.width + self.goals[:, 1]).tolist()
            self.priorities = np.where(changed, self.base_priority, self.priorities)
            self.best_distance[changed] = np.inf
            self.stalled[changed] = 0
        return changed

    def distance_map(self, agent: int) -> np.ndarray:
        """(H * W,) read-only distances to `agent`'s goal (-1 where unreachable): BFS steps, or
        guided costs (`DistanceTable.array`)."""
        return self.distances.array(self._goal_flat[agent])

    def _distance_list(self, agent: int) -> Sequence:
        """`distance_map(agent)` as the table's flat `array.array` (`DistanceTable.row`),
        unreachable cells above any path."""
        return self.distances.row(self._goal_flat[agent])

    def anchored_ranking(self, agent: int, cell: int) -> np.ndarray:
        """`agent`'s five actions at flat `cell` by distance to its goal: `distance_rankings`'
        row for one agent (what the anchor ranks by)."""
        return self.distance_rankings([cell], [agent])[0]

    def distance_rankings(self, flat, agents=None, rows=None) -> np.ndarray:
        """(len(flat), 5) plain PIBT's rankings: agent `agents[k]` (default k) at flat cell
        `flat[k]`, its actions by distance to its goal (closer first, blocked moves last),
        equal distances by this tick's hash. Under guidance an action's key is its step cost
        plus the distance from where it leads. One implementation for the anchor, the plan's
        rollout and every caller of `plan.distance_rankings`. `rows`: each agent's distance row
        as an array, where the caller has them at hand (the plan's rollout, tick after tick)."""
        flat = np.asarray(flat, dtype=np.int64)
        agents = np.arange(len(flat)) if agents is None else np.asarray(agents, dtype=np.int64)
        targets = self._targets[flat]
        # blocked moves at `unreachable`, as far as a cell the goal cannot be reached from
        key = np.full(targets.shape, float(self.distances.unreachable))
        for k, agent in enumerate(agents.tolist()):
            ok = targets[k] >= 0
            cells = targets[k, ok]
            if rows is not None:
                key[k, ok] = rows[k][cells]
                continue
            dist = self._distance_list(agent)  # a whole row, or a goal's window (`WindowRow`)
            key[k, ok] = np.asarray(dist)[cells] if isinstance(dist, memoryview) \
                else [dist[c] for c in cells.tolist()]
        if self._step_costs is not None:
            key = key + self._step_costs[flat]
        ties = tie_breakers(agents, self.tick)
        return np.lexsort((ties, key), axis=-1).astype(np.int64)

    # ------------------------------------------------------------------------------------------
    def check_fixed(self, fixed) -> np.ndarray:
        """`fixed` as an (N,) bool array of its own (None: nobody held); ValueError otherwise."""
        n = self.num_agents
        fixed = np.zeros(n, dtype=bool) if fixed is None else np.array(fixed, dtype=bool)
        if fixed.shape != (n,):
            raise ValueError(f"fixed must have shape ({n},), got {fixed.shape}")
        return fixed

    def split_reserved(self, reserved, occupant: dict[int, int]) -> tuple[list[int], list[int]]:
        """The reserved (row, col) cells on the map, flat: (the agents standing on one, which
        hold: it is theirs already, nobody else enters; the free ones, which nobody enters).
        `occupant`: flat cell -> the agent on it. Cells off the map are ignored."""
        held, free = [], []
        for cell in reserved:
            r, c = int(cell[0]), int(cell[1])
            if 0 <= r < self.height and 0 <= c < self.width:
                flat = r * self.width + c
                if flat in occupant:
                    held.append(occupant[flat])
                else:
                    free.append(flat)
        return held, free

    def check_positions(self, positions) -> np.ndarray:
        positions = np.asarray(positions)
        if positions.shape != (self.num_agents, 2):
            raise ValueError(f"positions must have shape ({self.num_agents}, 2), "
                             f"got {positions.shape}")
        positions = positions.astype(np.int64, copy=False)
        r, c = positions[:, 0], positions[:, 1]
        outside = (r < 0) | (r >= self.height) | (c < 0) | (c >= self.width)
        if outside.any():
            i = int(np.flatnonzero(outside)[0])
            raise ValueError(f"agent {i} at {tuple(positions[i].tolist())} is outside the "
                             f"{self.height}x{self.width} map")
        flat = r * self.width + c
        on_obstacle = self.grid.ravel()[flat]
        if on_obstacle.any():
            i = int(np.flatnonzero(on_obstacle)[0])
            raise ValueError(f"agent {i} at {tuple(positions[i].tolist())} is on an obstacle")
        return positions

    def _candidates(self, current: np.ndarray, prefs: np.ndarray) -> list[list[int]]:
        """Per agent the flat cells of its ranked actions, moves off the map or onto an
        obstacle left out (one table lookup; the search below is the only Python loop)."""
        return [[cell for cell in row if cell >= 0]
                for row in self._targets[current[:, None], prefs].tolist()]

    def step(self, positions, rankings, fixed=None, reserved=()) -> ShieldStep:
        """One tick: the next cells of every agent under PIBT with these rankings.

        positions: (N, 2) current cells (distinct free cells of the map).
        rankings: (N, 5) each row the actions 0..4 ranked, best first.
        fixed: optional (N,) bool: these agents stay and cannot be pushed (their rankings are
            ignored; e.g. a robot whose decision is missing, or one still driving).
        reserved: cells (row, col) no agent may enter (a moving robot's second cell); an agent
            standing on a reserved cell is held there like a fixed one.
        """
        positions = self.check_positions(positions)
        n = self.num_agents
        prefs = validate_rankings(rankings, n)
        fixed = self.check_fixed(fixed)
        w = self.width
        current_flat = positions[:, 0] * w + positions[:, 1]
        current = current_flat.tolist()
        asked = prefs
        top = self.anchored_agent(fixed)  # the highest priority: the first the loop takes
        if top >= 0:
            prefs = prefs.copy()
            prefs[top] = self.anchored_ranking(top, current[top])
        candidates = self._candidates(current_flat, prefs)
        occupied_now = {cell: i for i, cell in enumerate(current)}
        if len(occupied_now) != n:
            cells, counts = np.unique(current_flat, return_counts=True)
            cell = int(cells[counts > 1][0])
            who = np.flatnonzero(current_flat == cell).tolist()
            raise ValueError(f"agents {who} share the cell {divmod(cell, w)}")
        if self.hindrance:
            for i in np.flatnonzero(~fixed).tolist():
                candidates[i] = self._hindrance_order(i, candidates[i], current, occupied_now)
        occupied_next: dict[int, int] = {}
        decided = [-1] * n  # next flat cell per agent, -1 undecided
        fixed = fixed.copy()
        holders, kept_free = self.split_reserved(reserved, occupied_now)
        fixed[holders] = True
        for cell in kept_free:
            occupied_next[cell] = -2  # nobody's
        for i in np.flatnonzero(fixed).tolist():
            occupied_next[current[i]] = i
            decided[i] = current[i]
        partner_of = None
        if self.swap:
            def partner_of(i: int, target: int) -> int:
                return self._swap_partner(i, target, current, occupied_now, decided)
        push = Push(current, occupied_now, occupied_next, decided, candidates.__getitem__,
                    partner_of)
        for i in np.argsort(-self.priorities, kind="stable").tolist():
            if decided[i] < 0 and not push.funnel(i, -1) and current[i] not in occupied_next:
                push.assign(i, current[i])  # not pushed: staying is always possible

        nxt = np.asarray(decided, dtype=np.int64)
        if (nxt < 0).any():  # cannot happen: an unpushed agent can always stay
            raise RuntimeError(f"PIBT left agents {np.flatnonzero(nxt < 0).tolist()} undecided")
        new_positions = np.stack(np.divmod(nxt, w), axis=1)
        actions = self._action_of_delta[nxt - current_flat + w]
        overridden = (actions != asked[:, 0]) & ~fixed
        self.advance_priorities(new_positions)
        self.tick += 1
        return ShieldStep(new_positions, actions, overridden)

    def step_first(self, positions, asked, first, fixed, reserved, held) -> ShieldStep:
        """`step` with each agent's `first` action ranked first and its own ranking `asked` after
        it (the multi-step rules' tick: EPIBT's operations, the LNS plan); `overridden` against
        the agent's own first choice, as every rule reports it, never for `held` agents."""
        others = asked[asked != first[:, None]].reshape(len(asked), NUM_ACTIONS - 1)
        result = PIBTShield.step(self, positions, np.concatenate([first[:, None], others], axis=1),
                                 fixed=fixed, reserved=reserved)
        overridden = (result.actions != asked[:, 0]) & ~held
        return ShieldStep(result.positions, result.actions, overridden)

    def peek(self, positions, rankings, fixed=None, reserved=()) -> ShieldStep:
        """What `step` would command, the rule's state (priorities, tick, the patient anchor's
        clocks) left as it was: the one way to ask the rule without taking the tick."""
        state = self.snapshot()
        try:
            return self.step(positions, rankings, fixed=fixed, reserved=reserved)
        finally:
            self.restore(state)

    # --- hindrance ------------------------------------------------------------------------------
    def _hindrance_order(self, i: int, ranked: list[int], current: list[int],
                         occupied_now: dict[int, int]) -> list[int]:
        """`ranked` (agent i's candidate cells, best first) with every run of consecutive cells
        at equal distance to i's goal stably sorted by hindrance: how many agents next to i
        would lose a move closer to their goal if i took the cell."""
        if len(ranked) < 2:
            return ranked
        neighbours = [(c, occupied_now[c]) for c in self._neighbors[current[i]]
                      if c in occupied_now]
        if not neighbours:
            return ranked  # nobody to hinder (most agents on a sparse map): nothing to compute
        dist = self._distance_list(i)
        d = [dist[c] for c in ranked]
        if all(d[k] != d[k + 1] for k in range(len(d) - 1)):
            return ranked  # no ties
        neighbours = [(c, self._distance_list(j)) for c, j in neighbours]

        def hindrance(cell: int) -> int:
            return sum(1 for at, dj in neighbours if at != cell and dj[cell] < dj[at])

        out: list[int] = []
        start = 0
        for end in range(1, len(ranked) + 1):
            if end == len(ranked) or d[end] != d[start]:
                run = ranked[start:end]
                if len(run) > 1:
                    run = sorted(run, key=hindrance)  # stable: the ranking breaks equal counts
                out.extend(run)
                start = end
        return out

    # --- swap (lacam3) --------------------------------------------------------------------------
    def _swap_partner(self, i: int, target: int, current: list[int],
                      occupied_now: dict[int, int], decided: list[int]) -> int:
        """The agent agent i must swap with this tick (-1: none), i's first candidate `target`
        (`swap_partner` over the shield's distance lists)."""
        return swap_partner(i, target, current[i], occupied_now, decided, self._neighbors,
                            self._goal_flat, self._distance_list)

    def advance(self, positions) -> None:
        """A tick commanded by someone else (a kept plan) that left the agents at `positions`:
        the priorities advance and the tick counts, as after `step`."""
        self.advance_priorities(positions)
        self.tick += 1

    def advance_priorities(self, positions) -> None:
        """PIBT's dynamic priorities after a step that left the agents at `positions` (N, 2):
        back to the tie-breaker on the goal, one more off it. `step` calls it; a caller that
        holds every agent for a tick (an arbiter refusing a tick) calls it alone."""
        positions = np.asarray(positions)
        on_goal = (positions == self.goals).all(axis=1)
        self.priorities = np.where(on_goal, self.base_priority, self.priorities + 1.0)
        if self.anchor and self.anchor_patience:
            flat = (positions[:, 0] * self.width + positions[:, 1]).tolist()
            dist = np.fromiter((self._distance_list(i)[c] for i, c in enumerate(flat)),
                               dtype=np.float64, count=len(flat))
            closer = dist < self.best_distance
            self.best_distance = np.minimum(self.best_distance, dist)
            self.stalled = np.where(closer, 0, self.stalled + 1)
