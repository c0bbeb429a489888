"""The classical centralized reference: LaCAM or PIBT from the `pymapf` library (MIT, pinned
0.9.0, pure Python, CPU only).

Why pymapf: of the PyPI candidates checked here, `pymapf` installs with no dependency and has
LaCAM (Okumura 2023, complete) and PIBT (Okumura et al. 2022); `rt-lacam` needs a Zig compiler
to build, `cuplan` targets CUDA, and `pogema-toolbox` brings no planner of its own.

The planner solves the whole instance up front; its plan is then replayed through the same
environment and conflict rules as the learned policies, so every metric is measured in one
way. A plan longer than the step limit, or no plan within the time budget, is a failure.

Speed: most of pymapf's LaCAM time on a large map goes into one pure-Python Dijkstra per goal
(docs/results.md, "Performance (2-core machine, no GPU)"). We hand it our vectorised BFS
distances instead (identical values on a 4-connected unit grid, so identical plans;
`test_coordination_planners.py` checks that).
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass

import numpy as np

PLANNER_NAMES = ("lacam", "pibt")
LIBRARY = "pymapf"


def library_version() -> str:
    from importlib.metadata import version

    return f"{LIBRARY} {version(LIBRARY)}"


@dataclass(frozen=True)
class PlanResult:
    """`positions` (T+1, N, 2) from the starts; agents of unsolved components stay put."""

    positions: np.ndarray
    runtime: float
    unsolved_agents: int = 0
    reason: str = ""

    @property
    def complete(self) -> bool:
        return self.unsolved_agents == 0


def positions_to_actions(positions: np.ndarray) -> np.ndarray:
    """Convert a (T+1, N, 2) joint path to (T, N) actions in DHC order; raises ValueError on a
    jump that is not one grid move."""
    from mapf_fleet.grid.actions import ACTION_DELTAS

    positions = np.asarray(positions, dtype=np.int64)
    deltas = positions[1:] - positions[:-1]  # (T, N, 2)
    match = np.all(deltas[:, :, None, :] == np.asarray(ACTION_DELTAS)[None, None], axis=-1)
    if not match.any(axis=-1).all():
        t, i = np.argwhere(~match.any(axis=-1))[0]
        raise ValueError(f"plan moves agent {i} from {positions[t, i]} to {positions[t + 1, i]} at step {t}: not one grid move")
    return match.argmax(axis=-1).astype(np.int64)


def _distance_tables(grid: np.ndarray, goals: np.ndarray) -> list[dict]:
    """Per-goal {cell: distance} dicts, as pymapf's oracle stores them, from our numpy BFS."""
    from mapf_fleet.grid.heuristic import bfs_distances_many

    tables = []
    for dist in np.asarray(bfs_distances_many(grid, goals)):
        cells = np.argwhere(dist >= 0)  # UNREACHABLE is -1
        values = dist[cells[:, 0], cells[:, 1]].tolist()
        tables.append(dict(zip(map(tuple, cells.tolist()), values)))
    return tables


@contextlib.contextmanager
def _fast_distance_oracle(names: list[str], tables: list[dict]):
    """Temporarily give pymapf's planners precomputed distance tables. Touches a private class
    of the pinned version; when it is missing the planner just runs at its own speed."""
    try:
        from pymapf.algorithms import lacam as lacam_module
        from pymapf.algorithms import pibt as pibt_module

        original = pibt_module._DistanceOracle
    except (ImportError, AttributeError):
        yield
        return
    by_name = dict(zip(names, tables))

    class PrecomputedOracle(original):
        def __init__(self, grid, goals, allow_diagonals=False):
            if allow_diagonals or set(goals) - set(by_name):
                super().__init__(grid, goals, allow_diagonals)
            else:
                self._tables = {name: by_name[name] for name in goals}

    lacam_module._DistanceOracle = pibt_module._DistanceOracle = PrecomputedOracle
    try:
        yield
    finally:
        lacam_module._DistanceOracle = pibt_module._DistanceOracle = original


class ClassicalPlanner:
    """A centralized pymapf solver (`algorithm` "lacam" or "pibt") with a wall-clock budget per
    instance. `plan(grid, starts, goals)` returns a `PlanResult`."""

    def __init__(self, algorithm: str = "lacam", time_limit: float = 10.0, seed: int = 0, fast_distances: bool = True):
        if algorithm not in PLANNER_NAMES:
            raise ValueError(f"planner algorithm must be one of {PLANNER_NAMES}, got {algorithm!r}")
        if time_limit <= 0:
            raise ValueError(f"planner time_limit must be positive, got {time_limit}")
        self.algorithm = algorithm
        self.time_limit = float(time_limit)
        self.seed = int(seed)
        self.fast_distances = fast_distances

    def _solver(self):
        import pymapf

        return pymapf.get_solver(self.algorithm, time_limit=self.time_limit, seed=self.seed)

    def _solve(self, grid: np.ndarray, starts: np.ndarray, goals: np.ndarray) -> np.ndarray | None:
        """(T+1, n, 2) positions for one group of agents, or None (no plan in the budget)."""
        import pymapf

        names = [f"a{i}" for i in range(len(starts))]
        problem = pymapf.MAPFProblem(
            pymapf.GridMap(grid.astype(np.uint8)),
            [pymapf.Agent(n, tuple(map(int, s)), tuple(map(int, g))) for n, s, g in zip(names, starts, goals)],
        )
        oracle = (
            _fast_distance_oracle(names, _distance_tables(grid, goals)) if self.fast_distances else contextlib.nullcontext()
        )
        with oracle:
            solution = self._solver().solve(problem)
        if solution is None:
            return None
        horizon = max(len(solution.paths[n]) for n in names)
        return np.array(
            [[solution.position_at(n, t) for n in names] for t in range(horizon)], dtype=np.int64
        ).reshape(horizon, len(names), 2)

    def plan(self, grid: np.ndarray, starts: np.ndarray, goals: np.ndarray) -> PlanResult:
        """Plan each connected free region separately (agents of different regions never meet).
        Random instances put some agents in small pockets where they cannot pass each other;
        such a region has no plan, LaCAM usually proves it in milliseconds, and the agents of the
        solvable regions still get theirs. The time budget applies per region."""
        from mapf_fleet.grid.instance import free_components

        grid = np.asarray(grid) != 0
        starts = np.asarray(starts, dtype=np.int64)
        goals = np.asarray(goals, dtype=np.int64)
        began = time.perf_counter()
        region = free_components(grid)[starts[:, 0], starts[:, 1]]
        parts: list[tuple[np.ndarray, np.ndarray]] = []  # (agent indices, (T+1, n, 2))
        unsolved = 0
        for label in np.unique(region):
            idx = np.flatnonzero(region == label)
            if np.array_equal(starts[idx], goals[idx]):
                continue
            path = self._solve(grid, starts[idx], goals[idx])
            if path is None:
                unsolved += len(idx)
            else:
                parts.append((idx, path))
        horizon = max([len(p) for _, p in parts], default=1)
        positions = np.repeat(starts[None], horizon, axis=0)
        for idx, path in parts:
            positions[: len(path), idx] = path
            positions[len(path):, idx] = path[-1]
        reason = f"{unsolved} agent(s) in regions without a {self.algorithm} plan within {self.time_limit:g} s" if unsolved else ""
        return PlanResult(positions, time.perf_counter() - began, unsolved, reason)
