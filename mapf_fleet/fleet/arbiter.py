"""The tick's arbiter (numpy only, part of the fleet core): turns every robot's ranked decision into the cells
the robots are commanded to, with the configured conflict rule. The simulator and the real-robot
aggregator both call it; only the arbiter commands waypoints.

Rules (`CONFLICT_RULES`):
  pibt    `coordination.pibt.PIBTShield` over the robots' rankings (CS-PIBT): nobody's
          move is reverted, a robot in the way may be pushed to another of its ranked moves.
          The batched evaluator's `--conflict-rule pibt` (`evaluation.runner.run_decentralized`).
  pibt_anchor  the same, with the highest-priority robot on its distance order whatever it
          ranked (`PIBTShield(anchor=True)`; docs/results.md, "The anchor against plain PIBT").
  pibt[_anchor]_swap, pibt[_anchor][_swap]_hindrance  the same with lacam3's swap in
          corridors and/or the hindrance tie-break (`coordination.rules.Rule`; every
          guarantee below holds for each).
  lacam   the planning arbiter (`coordination.plan.PlanKeeper`): a kept LaCAM plan whose root
          step ranks each robot's moves by its ranking, re-planned when something leaves it,
          `planning_budget` seconds per re-plan (successors with swap, restarts for long
          first plans: `coordination.plan.ARBITER`); a tick without a plan is
          pibt_anchor_swap's step.
  revert  the paper's environment: `grid.env.resolve_moves` on the first choices (a conflicting
          move is reverted to "stay").

Held robots (`held`): a robot whose decision is missing, or (real robots) one that has not yet
reached its last waypoint, stays where it is and cannot be pushed. `reserved` cells are kept
free: the waypoint of a robot still driving there (it occupies both cells). With both rules the
commanded cells are then safe for real robots: each robot is commanded to its own cell or an
adjacent free cell that no other robot is commanded to, no two robots trade cells, no robot
enters a reserved cell, an obstacle or leaves the map (`unsafe_commands` checks exactly this).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mapf_fleet.coordination.factory import make_shield
from mapf_fleet.coordination.rules import CONFLICT_RULES, FLEET_RULE, Rule
from mapf_fleet.grid.actions import NUM_ACTIONS, STAY, actions_between

# The fleet's default: of the PIBT variants, the one that led on every family measured, one-shot
# and lifelong, with the heuristic and with the learned default (docs/results.md, "PIBT variants")
DEFAULT_CONFLICT_RULE = FLEET_RULE


def check_conflict_rule(rule: str) -> str:
    return Rule.parse(rule, "conflict_rule").name


def single_choice_ranking(action: int) -> list[int]:
    """The ranking of a robot that only gave its choice: [action, stay, the rest in order]."""
    action = int(action)
    if not 0 <= action < NUM_ACTIONS:
        raise ValueError(f"action {action} is not one of 0..{NUM_ACTIONS - 1}")
    rest = [a for a in range(NUM_ACTIONS) if a not in (action, STAY)]
    return [action] + ([STAY] if action != STAY else []) + rest


def ranking_problem(action: int, ranking) -> str:
    """"" when `ranking` (possibly empty) is a valid ranking whose first entry is `action`,
    else what is wrong with it."""
    prefs = [int(a) for a in ranking]
    if not prefs:
        return "" if 0 <= int(action) < NUM_ACTIONS else f"action {action} out of range"
    if sorted(prefs) != list(range(NUM_ACTIONS)):
        return f"ranking {prefs} is not a ranking of the actions 0..{NUM_ACTIONS - 1}"
    if prefs[0] != int(action):
        return f"action {action} is not the first of its ranking {prefs}"
    return ""


@dataclass(frozen=True)
class Resolution:
    """One arbitrated tick. `positions` (N, 2): each robot's commanded cell (the simulator's next
    positions); `actions` (N,): the executed actions; `overridden` (N,) bool: a robot with a
    decision whose executed action is not its first choice (pibt: pushed or yielded; revert:
    reverted); `collided` (N,) bool: moves reverted by `resolve_moves` (pibt: none);
    `held` (N,) bool: robots that stayed without a say (missing decision, still driving);
    `problem`: why every robot was told to stay instead ("" normally)."""

    positions: np.ndarray
    actions: np.ndarray
    overridden: np.ndarray
    collided: np.ndarray
    held: np.ndarray
    problem: str = ""

    @property
    def overridden_ids(self) -> list[int]:
        return np.flatnonzero(self.overridden).tolist()

    @property
    def collided_ids(self) -> list[int]:
        return np.flatnonzero(self.collided).tolist()


@dataclass
class TickArbiter:
    """The arbiter of one run: one map, one set of goals, one rule (PIBT keeps its priorities
    from tick to tick, exactly as the evaluator's one `PIBTShield` per episode)."""

    grid: np.ndarray
    goals: np.ndarray
    rule: str = DEFAULT_CONFLICT_RULE
    planning_budget: float | None = None  # lacam: seconds per re-plan (None: the default)
    guidance: object = None  # a grid.guidance.Guidance for the map (None: BFS distances)
    overridden_total: int = field(default=0, init=False)
    collided_total: int = field(default=0, init=False)

    def __post_init__(self):
        check_conflict_rule(self.rule)
        self.grid = np.asarray(self.grid) != 0
        self.goals = np.array(self.goals, dtype=np.int64)  # own copy: `set_goals` replaces it
        self.shield = make_shield(self.rule, self.grid, self.goals,
                                  planning_budget=self.planning_budget, guidance=self.guidance)

    def set_guidance(self, guidance) -> None:
        """Read distances under a new guidance graph from the next tick (online guidance)."""
        self.guidance = guidance
        if self.shield is not None:
            self.shield.set_guidance(guidance)

    def set_goals(self, goals) -> None:
        """New goals without rebuilding the arbiter (a fleet that takes goals at run time): the
        shield keeps its distance maps (per goal cell) and the priorities of robots whose goal
        did not change (`PIBTShield.set_goals`)."""
        goals = np.asarray(goals, dtype=np.int64)
        if goals.shape != self.goals.shape:
            raise ValueError(f"goals must have shape {self.goals.shape}, got {goals.shape}")
        self.goals = goals.copy()
        if self.shield is not None:
            self.shield.set_goals(self.goals)

    def boost(self, robots) -> None:
        """Put `robots` above every other robot in PIBT's priority (an idle robot clearing a
        busy robot's goal, `FleetRun`); no effect under "revert"."""
        if self.shield is not None and len(robots):
            shield = self.shield
            top = float(shield.priorities.max()) + 1.0
            shield.priorities[list(robots)] = top + shield.base_priority[list(robots)]

    def resolve(self, positions, rankings, held=None, reserved=()) -> Resolution:
        """Arbitrate one tick. positions (N, 2) the robots' cells; rankings (N, 5) each row a
        ranking (best first; a held robot's row is ignored); held (N,) bool; reserved: cells
        (row, col) kept free."""
        positions = np.asarray(positions, dtype=np.int64)
        prefs = np.asarray(rankings, dtype=np.int64)
        n = len(positions)
        held = np.zeros(n, dtype=bool) if held is None else np.asarray(held, dtype=bool).copy()
        reserved = [(int(r), int(c)) for r, c in reserved]
        problem = self._position_problem(positions)
        if problem:
            return self._all_stay(positions, held, problem)
        if self.shield is not None:
            step = self.shield.step(positions, prefs, fixed=held, reserved=reserved)
            actions = step.actions
            grid = self.grid
        else:
            actions, grid = self._revert_inputs(positions, prefs[:, 0], held, reserved)
        # the grid world's conflict rules, as the evaluator's env.step (pibt: nothing reverts)
        from mapf_fleet.grid.env import resolve_moves

        nxt, collided = resolve_moves(grid, positions, actions)
        nxt = np.asarray(nxt, dtype=np.int64)
        collided = np.asarray(collided, dtype=bool)
        executed = actions_between(positions, nxt)
        overridden = (executed != prefs[:, 0]) & ~held
        self.overridden_total += int(overridden.sum())
        self.collided_total += int(collided.sum())
        return Resolution(nxt, executed, overridden, collided, held)

    def _revert_inputs(self, positions, choices, held, reserved):
        """The paper's rule with held robots and reserved cells: a held robot stays (so a move
        into its cell reverts, as any move into a staying robot's cell); a reserved cell is an
        obstacle for this tick, except where a robot stands on it (that robot is held)."""
        actions = np.where(held, STAY, choices).astype(np.int64)
        grid = self.grid
        if reserved:
            grid = grid.copy()
            occupant = {(int(r), int(c)): i for i, (r, c) in enumerate(positions.tolist())}
            h, w = grid.shape
            for cell in reserved:
                if cell in occupant:
                    actions[occupant[cell]] = STAY
                    held[occupant[cell]] = True
                elif 0 <= cell[0] < h and 0 <= cell[1] < w:
                    grid[cell] = True
        return actions, grid

    def _position_problem(self, positions) -> str:
        h, w = self.grid.shape
        r, c = positions[:, 0], positions[:, 1]
        outside = (r < 0) | (r >= h) | (c < 0) | (c >= w)
        if outside.any():
            return f"robots {np.flatnonzero(outside).tolist()} are off the {h}x{w} map"
        blocked = self.grid[r, c]
        if blocked.any():
            return f"robots {np.flatnonzero(blocked).tolist()} stand on obstacles"
        cells, counts = np.unique(r * w + c, return_counts=True)
        if (counts > 1).any():
            shared = [(int(x) // w, int(x) % w) for x in cells[counts > 1]]
            return f"robots share cells {shared}"
        return ""

    def _all_stay(self, positions, held, problem: str) -> Resolution:
        n = len(positions)
        if self.shield is not None:
            self.shield.advance_priorities(positions)  # as if everyone stayed
        return Resolution(positions.copy(), np.full(n, STAY, dtype=np.int64),
                          np.zeros(n, dtype=bool), np.zeros(n, dtype=bool), held, problem)


def unsafe_commands(grid, positions, commanded, held=None, reserved=()) -> list[str]:
    """What breaks the real-robot rule in these commands ([] when they are safe): every robot is
    commanded to its own cell or an adjacent free cell of the map; no two robots to one cell;
    no two robots trading cells; a held robot stays; nobody else enters a reserved cell or a
    held robot's cell."""
    grid = np.asarray(grid) != 0
    positions = np.asarray(positions, dtype=np.int64)
    commanded = np.asarray(commanded, dtype=np.int64)
    n = len(positions)
    held = np.zeros(n, dtype=bool) if held is None else np.asarray(held, dtype=bool)
    h, w = grid.shape
    problems = []
    step = np.abs(commanded - positions).sum(axis=1)
    for i in np.flatnonzero(step > 1).tolist():
        problems.append(f"robot {i} commanded {step[i]} cells away")
    r, c = commanded[:, 0], commanded[:, 1]
    inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    for i in np.flatnonzero(~inside).tolist():
        problems.append(f"robot {i} commanded off the map to {tuple(commanded[i].tolist())}")
    for i in np.flatnonzero(inside).tolist():
        if grid[r[i], c[i]]:
            problems.append(f"robot {i} commanded onto an obstacle {tuple(commanded[i].tolist())}")
    cells: dict[tuple, int] = {}
    for i, cell in enumerate(map(tuple, commanded.tolist())):
        if cell in cells:
            problems.append(f"robots {cells[cell]} and {i} commanded to one cell {cell}")
        cells[cell] = i
    now = {cell: i for i, cell in enumerate(map(tuple, positions.tolist()))}
    for i in range(n):
        j = now.get(tuple(commanded[i].tolist()), -1)
        if j > i and j != i and tuple(commanded[j].tolist()) == tuple(positions[i].tolist()):
            problems.append(f"robots {i} and {j} commanded to trade cells")
    for i in np.flatnonzero(held).tolist():
        if (commanded[i] != positions[i]).any():
            problems.append(f"held robot {i} commanded to move")
    blocked = {tuple(int(v) for v in cell) for cell in reserved}
    blocked |= {tuple(positions[i].tolist()) for i in np.flatnonzero(held)}
    for i in range(n):
        cell = tuple(commanded[i].tolist())
        if cell in blocked and cell != tuple(positions[i].tolist()):
            problems.append(f"robot {i} commanded into the occupied cell {cell}")
    return problems


# ---- real robots: executing a resolved tick safely -------------------------------------------
# The grid world (and PIBT) let a robot enter a cell in the tick its occupant leaves it
# (following, rotations). Real robots move at their own pace, so the aggregator sends a
# follower its waypoint only once the occupant has reported leaving (`ready_to_send`), and a
# rotation (a cycle of followers: nobody could go first) stays put (`break_rotations`).

def break_rotations(positions, commanded) -> tuple[np.ndarray, list[int]]:
    """Commands without cycles of followers: each robot of a cycle (robot i commanded into the
    cell of robot j, j into k's, ..., back to i) is told to stay instead; (commands, their ids).
    Commands into distinct cells give each cell at most one follower, so nobody else was
    heading into a cycle member's cell: the result is still safe."""
    positions = np.asarray(positions, dtype=np.int64)
    commanded = np.asarray(commanded, dtype=np.int64).copy()
    occupant = {cell: i for i, cell in enumerate(map(tuple, positions.tolist()))}
    successor = {}
    for i in range(len(positions)):
        if (commanded[i] != positions[i]).any():
            j = occupant.get(tuple(commanded[i].tolist()), -1)
            if j >= 0:
                successor[i] = j
    stopped: set[int] = set()
    done: set[int] = set()
    for start in successor:
        path, i = [], start
        while i in successor and i not in done and i not in path:
            path.append(i)
            i = successor[i]
        if i in path:  # a cycle: from i round to i
            stopped.update(path[path.index(i):])
        done.update(path)
    ids = sorted(stopped)
    commanded[ids] = positions[ids]
    return commanded, ids


def ready_to_send(commanded, reported: dict, pending, unsure=None) -> list[int]:
    """Robots among `pending` whose commanded cell no other robot reports being in now
    (`reported`: robot id -> its latest reported cell; `unsure`: robot id -> a cell it may still
    be in, e.g. the last valid cell of a robot whose pose is rejected)."""
    held_by: dict[tuple, set] = {}
    for cells in (reported, unsure or {}):
        for j, cell in cells.items():
            held_by.setdefault(tuple(int(v) for v in cell), set()).add(int(j))
    ready = []
    for i in pending:
        there = held_by.get(tuple(int(v) for v in commanded[i]), set()) - {int(i)}
        if not there:
            ready.append(int(i))
    return ready


@dataclass(frozen=True)
class PoseCheck:
    """A reported pose checked (`check_pose`): `cell` when accepted, else None and `reason`;
    `raw`: the cell the pose lies in (None for a non-finite coordinate)."""

    cell: tuple | None
    reason: str
    raw: tuple | None


def check_pose(grid, geometry, x, y, last=None) -> PoseCheck:
    """Check a robot's reported pose (x, y) against the map (`geometry`: a
    `common.MapGeometry`) and its last accepted cell `last` (None: its first pose). Rejected: a
    coordinate that is not a finite number (NaN, inf: the reason names the field and value), a
    cell off the grid or on an obstacle, or a cell more than one move from `last` (robots move
    one cell per tick, to a 4-neighbour: a jump means a bad pose or a lost localisation)."""
    for field_name, value in (("pose.position.x", x), ("pose.position.y", y)):
        try:
            finite = np.isfinite(float(value))
        except (TypeError, ValueError):
            finite = False
        if not finite:
            return PoseCheck(None, f"{field_name} is {value!r}, not a finite number", None)
    raw = tuple(int(v) for v in geometry.xy_to_cell(float(x), float(y)))
    h, w = np.asarray(grid).shape
    row, col = raw
    if not (0 <= row < h and 0 <= col < w):
        return PoseCheck(None, f"off the {h}x{w} grid (cell {row},{col})", raw)
    if grid[row][col]:
        return PoseCheck(None, f"on an obstacle (cell {row},{col})", raw)
    if last is not None:
        last = tuple(int(v) for v in last)
        jump = abs(row - last[0]) + abs(col - last[1])
        if jump > 1:
            return PoseCheck(None, f"a jump of {jump} cells from cell {last[0]},{last[1]} to "
                                   f"{row},{col} (robots move one cell at a time)", raw)
    return PoseCheck(raw, "", raw)


@dataclass(frozen=True)
class RobotCommands:
    """One real-robot tick's commands (`plan_robot_commands`). `waypoints` (N, 2): each robot's
    commanded cell (in transit: its old waypoint); `executed` (N,): the actions commanded this
    tick (held robots: stay); `late` (N,) bool: in transit; `reserved`: their waypoints;
    `stopped`: robots of a rotation told to stay; `problems`: why every robot stays ([] normally)."""

    waypoints: np.ndarray
    executed: np.ndarray
    resolution: Resolution
    late: np.ndarray
    reserved: list
    stopped: list
    problems: list


def plan_robot_commands(arbiter: TickArbiter, positions, waypoints, rankings,
                        missing=()) -> RobotCommands:
    """The real-robot arbiter's decision for one tick. positions (N, 2): the robots' cells in the
    tick's state; waypoints (N, 2): their last commanded cells; a robot whose cell is not its
    waypoint has not arrived: it is held and occupies both cells (its waypoint is reserved and
    stays its command). Robots in `missing` (no decision) are held. Rotations stay put; the
    commands are checked with `unsafe_commands`, and any breach makes every robot stay."""
    positions = np.asarray(positions, dtype=np.int64)
    waypoints = np.asarray(waypoints, dtype=np.int64)
    late = (positions != waypoints).any(axis=1)
    held = late.copy()
    held[list(missing)] = True
    reserved = [tuple(int(v) for v in waypoints[i]) for i in np.flatnonzero(late)]
    result = arbiter.resolve(positions, rankings, held=held, reserved=reserved)
    commanded, stopped = break_rotations(positions, result.positions)
    problems = ([result.problem] if result.problem else
                unsafe_commands(arbiter.grid, positions, commanded, result.held, reserved))
    if problems:
        commanded, stopped = positions.copy(), []
    commanded[late] = waypoints[late]  # still driving there: keep its waypoint
    executed = np.where(result.held, STAY, actions_between(positions, commanded))
    return RobotCommands(commanded, executed, result, late, reserved, stopped, problems)
