"""LaCAM over the robots' rankings: the planning arbiter's planner (numpy and the standard library).

LaCAM (Okumura, AAAI 2023) searches the space of configurations (one cell per agent) depth
first. Each high-level node holds a configuration and a queue of low-level constraints ("agent
i goes to cell v next", built lazily one agent deeper at a time); each time a node is visited
one constraint is popped and PIBT, honouring it, generates one successor configuration. The
search is complete: the constraint queue eventually enumerates every successor, so an
unsolvable instance exhausts the search and a solvable one is found.

What is ours:
- The PIBT step that generates configurations ranks an agent's moves by a **given ranking at
  the root** (the robots' submitted rankings: a learned policy's, or distance order for plain
  PIBT), and by **distance to the goal deeper in the search** (ties by a seeded random key, as
  PIBT's tie-breakers: with a fixed order PIBT livelocks). LaGAT (AAAI 2026) puts learned
  rankings into LaCAM's generator the same way.
- The root may hold **fixed** agents (they stay on the first step: a real robot still driving)
  and **reserved** cells (kept free on the first step): the plan starts with a step the arbiter
  may command.
- A known configuration found again is pushed back onto the stack (lacam2's re-insertion)
  instead of being dropped: it leaves dead ends sooner.
- Distances come from the map's shared `grid.heuristic.DistanceTable` (BFS steps, or least path
  costs under a guidance graph: then deeper candidates are ordered by step cost plus distance);
  the search runs on flat cell ids and Python sequences (no per-step numpy calls).
- One PIBT push (`push.Push`) serves this generator and the shield's tick.
- Budget: wall-clock seconds and a node count; the same inputs and seed give the same plan.

The plans are valid by construction (one move or a wait per agent per step, no two agents in a
cell, no two agents trading cells, no obstacle): `check_plan` verifies one, the tests run it on
every plan.
"""

from __future__ import annotations

import random
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from mapf_fleet.grid.heuristic import distance_table

from .push import Push
from .ranking import validate_rankings
from .swap import swap_partner


@dataclass(frozen=True)
class LaCAMResult:
    """`positions` (T+1, N, 2) from the start configuration to the goals, or None when no plan
    was found (`reason` says why: budget spent, or the search space exhausted); `nodes`: the
    high-level nodes generated; `seconds`: wall-clock time of the call."""

    positions: np.ndarray | None
    nodes: int
    seconds: float
    reason: str = ""
    # where some regions have a plan and others not: their plans (agents of the unplanned
    # regions stay put), and the (N,) bool mask of those agents
    partial: np.ndarray | None = None
    unsolved: np.ndarray | None = None

    @property
    def solved(self) -> bool:
        return self.positions is not None


class _Node:
    __slots__ = ("config", "parent", "order", "priorities", "tree", "occupied", "depth")

    def __init__(self, config, parent, order, priorities, depth):
        self.config = config  # tuple of flat cells
        self.parent = parent
        self.order = order  # agents by decreasing priority
        self.priorities = priorities
        # low-level constraint tree: (who, where) tuples, breadth first
        self.tree = deque([((), ())])
        self.occupied = None  # {cell: agent}, built when first needed
        self.depth = depth


class LaCAM:
    """LaCAM for one map. `plan(starts, goals, ...)` returns a `LaCAMResult`.

    grid: (H, W), nonzero = obstacle. seed: the tie-breaking seed (plans are deterministic for
    a seed). swap: the successor generator is lacam3's PIBT with swap (`swap.swap_partner`):
    two agents meeting head-on in a corridor back out to a branch and pass there, where plain
    PIBT's successors only push the one in front ahead (lacam3 measured it the largest single
    gain on dense instances; docs/results.md, "The expert ceiling"). guidance: a
    `grid.guidance.Guidance` for the map (None: BFS steps)."""

    def __init__(self, grid, seed: int = 0, swap: bool = False, guidance=None):
        grid = np.asarray(grid)
        if grid.ndim != 2:
            raise ValueError(f"grid must be 2-D, got shape {grid.shape}")
        self.grid = grid != 0
        self.height, self.width = self.grid.shape
        self.seed = int(seed)
        self.swap = bool(swap)
        self.table = distance_table(self.grid, guidance)
        # _targets[cell, action]: the flat cell an action leads to, -1 off the map, into an
        # obstacle or against a one-way lane
        self._targets = self.table.move_targets()
        # per cell: its free neighbours then itself (the candidates deeper in the search)
        self._moves = [[c for c in row[1:] if c >= 0] + [int(row[0])]
                       for row in self._targets.tolist()]
        self._neighbors = [m[:-1] for m in self._moves]
        self._step_costs = (None if self.table.step_costs is None
                            else self.table.step_costs.tolist())
        self._target_lists = self._targets.tolist()
        self._regions = None  # free-region labels, computed when first needed

    # ------------------------------------------------------------------------------------------
    def distances(self, goals_flat: list[int]) -> list:
        """Per agent the distance row (`DistanceTable.row`, flat cells) to its goal; unreachable
        cells hold `self.table.unreachable`."""
        self.table.reserve(len(goals_flat))  # every agent's row is read at every node
        row = self.table.row
        return [row(g) for g in goals_flat]

    def _flat(self, cells, name: str) -> list[int]:
        cells = np.asarray(cells, dtype=np.int64)
        if cells.ndim != 2 or cells.shape[1] != 2:
            raise ValueError(f"{name} must have shape (N, 2), got {cells.shape}")
        r, c = cells[:, 0], cells[:, 1]
        bad = (r < 0) | (r >= self.height) | (c < 0) | (c >= self.width)
        bad[~bad] = self.grid[r[~bad], c[~bad]]
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"{name}: agent {i} at {tuple(cells[i].tolist())} is off the map "
                             f"or on an obstacle")
        return (r * self.width + c).tolist()

    def plan(self, starts, goals, rankings=None, priorities=None, fixed=None, reserved=(),
             time_limit: float = 1.0, max_nodes: int = 1_000_000) -> LaCAMResult:
        """A plan from `starts` to `goals` ((N, 2) cells each), arguments as `plan_region`.

        Agents of different free regions of the map never meet: each region is planned on its
        own, smallest first, within the one deadline (random maps cut off small pockets whose
        search is short, where one joint search over every agent can spend the budget in the
        pocket's combinatorics). When some regions have no plan, `partial` holds the others'."""
        began = time.perf_counter()
        starts = np.asarray(starts, dtype=np.int64)
        goals = np.asarray(goals, dtype=np.int64)
        self._flat(starts, "starts")
        if len(starts) == 0:
            return LaCAMResult(np.zeros((1, 0, 2), dtype=np.int64), 0, 0.0)
        if self._regions is None:
            from mapf_fleet.grid.instance import free_components

            self._regions = free_components(self.grid)
        region = self._regions[starts[:, 0], starts[:, 1]]
        labels, counts = np.unique(region, return_counts=True)
        if len(labels) == 1:
            return self.plan_region(starts, goals, rankings, priorities, fixed, reserved,
                                    time_limit, max_nodes)
        n = len(starts)
        pieces, nodes, reasons = [], 0, []
        unsolved = np.zeros(n, dtype=bool)
        rankings = None if rankings is None else validate_rankings(rankings, n)
        fixed = None if fixed is None else np.asarray(fixed, dtype=bool)
        for label in labels[np.argsort(counts, kind="stable")]:
            idx = np.flatnonzero(region == label)
            if np.array_equal(starts[idx], goals[idx]):
                continue
            left = time_limit - (time.perf_counter() - began)
            result = self.plan_region(
                starts[idx], goals[idx], None if rankings is None else rankings[idx],
                None if priorities is None else np.asarray(priorities)[idx],
                None if fixed is None else fixed[idx], reserved, max(left, 0.0),
                max_nodes - nodes)
            nodes += result.nodes
            if result.solved:
                pieces.append((idx, result.positions))
            else:
                unsolved[idx] = True
                reasons.append(f"{len(idx)} agent(s): {result.reason}")
        horizon = max([len(p) for _, p in pieces], default=1)
        positions = np.repeat(starts[None], horizon, axis=0)
        for idx, path in pieces:
            positions[: len(path), idx] = path
            positions[len(path):, idx] = path[-1]
        seconds = time.perf_counter() - began
        if unsolved.any():
            return LaCAMResult(None, nodes, seconds, "; ".join(reasons), positions, unsolved)
        return LaCAMResult(positions, nodes, seconds)

    def plan_region(self, starts, goals, rankings=None, priorities=None, fixed=None, reserved=(),
                    time_limit: float = 1.0, max_nodes: int = 1_000_000) -> LaCAMResult:
        """A plan from `starts` to `goals` ((N, 2) cells each) by one joint search.

        rankings: optional (N, 5) actions best first: the root step's move order per agent
            (default: distance order).
        priorities: optional (N,) the root's PIBT priorities (default: PIBT's tie-breakers
            i / (N + 1)); deeper nodes update them as PIBT does (one more per step off the goal).
        fixed: optional (N,) bool: agents that stay on the first step.
        reserved: cells (row, col) no agent enters on the first step (an agent standing on one
            stays, as a fixed one).
        time_limit: wall-clock seconds; max_nodes: high-level nodes generated at most."""
        began = time.perf_counter()
        deadline = began + float(time_limit)
        start = self._flat(starts, "starts")
        goal = self._flat(goals, "goals")
        n = len(start)
        if len(goal) != n:
            raise ValueError(f"starts and goals differ in length: {n} vs {len(goal)}")
        if len(set(start)) != n:
            raise ValueError("starts: two agents share a cell")
        if len(set(goal)) != n:
            raise ValueError("goals: two agents share a goal cell")
        dist = self.distances(goal)
        far = self.table.unreachable
        unreachable = [i for i in range(n) if dist[i][start[i]] >= far]
        if unreachable:
            return LaCAMResult(None, 0, time.perf_counter() - began,
                               f"agents {unreachable[:8]} cannot reach their goals")
        base = [i / (n + 1) for i in range(n)]
        prio = list(base) if priorities is None else [float(p) for p in priorities]
        if len(prio) != n:
            raise ValueError(f"priorities must have length {n}, got {len(prio)}")
        root_candidates = None
        if rankings is not None:
            ranks = validate_rankings(rankings, n)
            table = self._targets[np.asarray(start)[:, None], ranks].tolist()
            root_candidates = [[c for c in row if c >= 0] for row in table]
        held = [False] * n if fixed is None else [bool(x) for x in np.asarray(fixed, dtype=bool)]
        if len(held) != n:
            raise ValueError(f"fixed must have length {n}, got {len(held)}")
        blocked = {}
        where_now = {c: i for i, c in enumerate(start)}
        for cell in reserved:
            r, c = int(cell[0]), int(cell[1])
            if 0 <= r < self.height and 0 <= c < self.width:
                flat = r * self.width + c
                if flat in where_now:
                    held[where_now[flat]] = True
                else:
                    blocked[flat] = -2
        rng = random.Random(self.seed)

        goal_t = tuple(goal)
        root_order = sorted(range(n), key=lambda i: -prio[i])
        held_ids = [i for i in root_order if held[i]]
        root = _Node(tuple(start), None, held_ids + [i for i in root_order if not held[i]],
                     prio, 0)
        # the fixed agents are the root's first constraints: every successor keeps them
        root.tree = deque([(tuple(held_ids), tuple(start[i] for i in held_ids))])
        explored = {root.config: root}
        stack = [root]
        nodes = 1
        moves = self._moves
        while stack:
            if nodes >= max_nodes:
                return LaCAMResult(None, nodes, time.perf_counter() - began,
                                   f"node budget ({max_nodes}) spent")
            if time.perf_counter() > deadline:
                return LaCAMResult(None, nodes, time.perf_counter() - began,
                                   f"time budget ({time_limit:g} s) spent")
            node = stack[-1]
            if node.config == goal_t:
                return LaCAMResult(self._positions(node), nodes, time.perf_counter() - began)
            if not node.tree:
                stack.pop()
                continue
            who, where = node.tree.popleft()
            depth = len(who)
            if depth < n:  # one agent deeper: every cell it may take next
                i = node.order[depth]
                here = node.config[i]
                if node is root and root_candidates is not None:
                    options = root_candidates[i]
                else:
                    options = list(moves[here])
                    rng.shuffle(options)
                for cell in options:
                    node.tree.append((who + (i,), where + (cell,)))
            if node is root:
                nxt = self._generate(node, who, where, dist, goal, rng, root_candidates, blocked)
            else:
                nxt = self._generate(node, who, where, dist, goal, rng, None, None)
            if nxt is None:
                continue
            known = explored.get(nxt)
            if known is not None:
                stack.append(known)  # re-insertion (lacam2)
                continue
            parent_prio = node.priorities
            child_prio = [base[i] if nxt[i] == goal[i] else parent_prio[i] + 1.0
                          for i in range(n)]
            order = sorted(range(n), key=child_prio.__getitem__, reverse=True)
            child = _Node(nxt, node, order, child_prio, node.depth + 1)
            explored[nxt] = child
            stack.append(child)
            nodes += 1
        return LaCAMResult(None, nodes, time.perf_counter() - began,
                           f"no plan exists ({EXHAUSTED})")

    # ------------------------------------------------------------------------------------------
    def _generate(self, node, who, where, dist, goal, rng, root_candidates, blocked):
        """PIBT's next configuration from `node` under the constraint (who, where), or None."""
        now = node.config
        occ_now = node.occupied
        if occ_now is None:
            occ_now = node.occupied = {c: i for i, c in enumerate(now)}
        n = len(now)
        nxt = [-1] * n
        occ_next = dict(blocked) if blocked else {}
        for i, cell in zip(who, where):
            if cell in occ_next:
                return None
            k = occ_now.get(cell, -1)
            if k >= 0 and k != i and nxt[k] == now[i]:
                return None  # two constrained agents trading cells
            nxt[i] = cell
            occ_next[cell] = i
        moves = self._moves
        rand = rng.random
        costs = self._step_costs
        targets = self._target_lists

        def candidates(i: int) -> list[int]:
            if root_candidates is not None:
                return root_candidates[i]
            here = now[i]
            d = dist[i]
            if costs is not None:
                # guided: step cost plus the distance from where it leads (stay: the wait
                # cost), ties in a random order drawn afresh each call
                step = costs[here]
                keyed = [(d[c] + step[a], rand(), c)
                         for a, c in enumerate(targets[here]) if c >= 0]
                keyed.sort()
                return [c for _, _, c in keyed]
            # distance first, ties in a random order drawn afresh each call (PIBT's tie-breaks;
            # drawing it once per search solved fewer dense instances). On a 4-connected grid a
            # neighbour is one step closer or one step farther: no sort needed.
            dh = d[here]
            closer, away = [], []
            for c in moves[here]:
                if c != here:
                    (closer if d[c] < dh else away).append(c)
            if len(closer) > 1:
                closer.sort(key=lambda _: rand())
            if len(away) > 1:
                away.sort(key=lambda _: rand())
            closer.append(here)
            return closer + away

        partner_of = None
        if self.swap:
            def partner_of(i: int, target: int) -> int:
                return swap_partner(i, target, now[i], occ_now, nxt, self._neighbors, goal,
                                    dist.__getitem__)
        push = Push(now, occ_now, occ_next, nxt, candidates, partner_of)
        for i in node.order:
            if nxt[i] < 0 and not push.funnel(i, -1):
                return None  # even staying is taken (by a constraint): no successor
        return tuple(nxt)

    def _positions(self, node) -> np.ndarray:
        configs = []
        while node is not None:
            configs.append(node.config)
            node = node.parent
        configs.reverse()
        flat = np.asarray(configs, dtype=np.int64)
        return np.stack(np.divmod(flat, self.width), axis=-1)


def check_plan(grid, positions, starts=None, goals=None) -> list[str]:
    """What is wrong with a joint plan (T+1, N, 2) on `grid` ([] when it is valid): a jump of
    more than one cell, an obstacle or off-map cell, two agents in one cell, two agents trading
    cells; optionally a wrong first or last configuration."""
    grid = np.asarray(grid) != 0
    p = np.asarray(positions, dtype=np.int64)
    problems = []
    if p.ndim != 3 or p.shape[2] != 2:
        return [f"plan must have shape (T+1, N, 2), got {p.shape}"]
    h, w = grid.shape
    r, c = p[..., 0], p[..., 1]
    inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    if not inside.all():
        t, i = np.argwhere(~inside)[0]
        problems.append(f"agent {i} off the map at step {t}")
        return problems
    if grid[r, c].any():
        t, i = np.argwhere(grid[r, c])[0]
        problems.append(f"agent {i} on an obstacle at step {t}")
    jumps = np.abs(np.diff(p, axis=0)).sum(axis=-1)
    if (jumps > 1).any():
        t, i = np.argwhere(jumps > 1)[0]
        problems.append(f"agent {i} jumps {jumps[t, i]} cells at step {t}")
    flat = r * w + c
    for t in range(len(flat)):
        if len(np.unique(flat[t])) != flat.shape[1]:
            problems.append(f"two agents share a cell at step {t}")
        if t:
            before = {cell: i for i, cell in enumerate(flat[t - 1].tolist())}
            for i, cell in enumerate(flat[t].tolist()):
                j = before.get(cell, -1)
                if j >= 0 and j != i and flat[t, j] == flat[t - 1, i]:
                    problems.append(f"agents {i} and {j} trade cells at step {t}")
                    break
    if starts is not None and not np.array_equal(p[0], np.asarray(starts)):
        problems.append("the plan does not start at the starts")
    if goals is not None and not np.array_equal(p[-1], np.asarray(goals)):
        problems.append("the plan does not end at the goals")
    return problems


SOLVABILITY_NODES = 50_000  # the node budget of `solvability` (the expert ceiling's, per search)
EXHAUSTED = "search space exhausted"  # in `LaCAMResult.reason` when a region has no plan


def solvability(grid, starts, goals, max_nodes: int = SOLVABILITY_NODES) -> tuple[str, int | None]:
    """("unsolvable" | "solved" | "undecided", the makespan of the plan found or None): LaCAM
    with swap from the starts within `max_nodes`. LaCAM is complete, so a search that exhausts a
    free region's configurations proves the instance has no plan (generated maps shut agents
    into dead-end pockets where they cannot pass each other); "undecided": the budget ran out."""
    result = LaCAM(grid, seed=0, swap=True).plan(starts, goals, time_limit=float("inf"),
                                                 max_nodes=max_nodes)
    if result.solved:
        return "solved", len(result.positions) - 1
    # one region proven without a plan settles it, whatever the other regions' budget did
    return ("unsolvable" if EXHAUSTED in result.reason else "undecided"), None


__all__ = ["LaCAM", "LaCAMResult", "check_plan", "solvability"]
