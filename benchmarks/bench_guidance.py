"""What guidance costs: guided distances for a new goal beside today's BFS, and the PIBT tick with
and without a guidance graph (issue 41's targets: a new goal's guided distances no slower than 2x
BFS; a tick at 64 agents <= 50 ms, at 2,048 agents lifelong <= 1 s, guidance included).

    python benchmarks/bench_guidance.py [--sizes 40 80 256] [--goals 200] [--repeat 1] [--json OUT]

Per map side (random maps, density 0.2): median milliseconds per new goal, fresh tables each
time (no cache hits), without guidance (BFS) and under the hand-made highways and a cost model
(`grid.guided_kernel`), three ways: `row` (the table's row, as the conflict rules and the
fleet's goal choices read it), `array` (the row and `DistanceTable.array`'s -1 copy of it, which
nothing in the fleet reads per goal any more) and `search` (the table's searcher alone, its row
and bits dropped: no new memory kept); and scipy's Dijkstra on the same graph
with the array built from it as `DistanceTable.array` builds it (the guided search before
`guided_kernel`; its bits cost more on top). Then the plain PIBT tick (fleet rule, distance
rankings) at 64 and 2,048 agents.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from scipy.sparse.csgraph import dijkstra

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mapf_fleet.coordination.factory import make_shield  # noqa: E402
from mapf_fleet.coordination.plan import distance_rankings  # noqa: E402
from mapf_fleet.coordination.rules import FLEET_RULE  # noqa: E402
from mapf_fleet.grid.guidance_made import CostModel, highways  # noqa: E402
from mapf_fleet.grid.guided_kernel import GuidedSearcher  # noqa: E402
from mapf_fleet.grid.heuristic import DistanceTable  # noqa: E402
from mapf_fleet.grid.maps import place_agents  # noqa: E402
from mapf_fleet.grid.search_kernel import Searcher  # noqa: E402


def _median_ms(read, goals) -> float:
    times = []
    for g in goals:
        began = time.perf_counter()
        read(int(g))
        times.append(time.perf_counter() - began)
    return 1e3 * statistics.median(times)


def per_goal_ms(blocked, guidance, goals, view: str = "array") -> float:
    """A new goal's distances from a fresh `DistanceTable` (`view`: "array" or "row")."""
    table = DistanceTable(blocked, guidance)
    table.array(int(goals[-1]))  # compiled code loaded before the clock runs
    return _median_ms(getattr(table, view), goals[:-1])


def search_ms(blocked, guidance, goals) -> float:
    """A new goal's row and bits from the table's own searcher alone (`Searcher` without
    guidance, `GuidedSearcher` with), handed back and dropped: the search without the table's
    keeping (new memory for every row and array it keeps)."""
    searcher = (Searcher(blocked) if guidance is None
                else GuidedSearcher(blocked, guidance.step_costs()))
    searcher.search([int(goals[-1])])
    return _median_ms(lambda goal: searcher.search([goal]), goals[:-1])


def scipy_ms(guidance, goals) -> float:
    """scipy's Dijkstra on the guidance's reverse graph, and the -1 array from its row, both kept
    as a table keeps them (the guided `DistanceTable.array` before `guided_kernel`)."""
    graph, kept = guidance.reverse_graph(), []

    def read(goal):
        row = dijkstra(graph, directed=True, indices=goal)
        kept.append((row, np.where(row >= np.inf, -1, row).astype(np.float64)))

    return _median_ms(read, goals[:-1])


def tick_ms(blocked, agents, guidance, ticks, rng) -> float:
    inst = place_agents(blocked.astype(np.uint8), agents, rng)
    shield = make_shield(FLEET_RULE, blocked, inst.goals, guidance=guidance)
    positions = np.asarray(inst.starts)
    shield.step(positions, distance_rankings(shield, positions))  # distances searched
    times = []
    for _ in range(ticks):
        began = time.perf_counter()
        step = shield.step(positions, distance_rankings(shield, positions))
        times.append(time.perf_counter() - began)
        positions = step.positions
    return 1e3 * statistics.median(times)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", nargs="+", type=int, default=[40, 80, 256])
    p.add_argument("--goals", type=int, default=200)
    p.add_argument("--ticks", type=int, default=20)
    p.add_argument("--repeat", type=int, default=1,
                   help="rounds of the distance figures (each figure: the median of its rounds)")
    p.add_argument("--json")
    args = p.parse_args()
    rng = np.random.default_rng(0)
    model = CostModel.from_vector(rng.normal(0, 0.5, len(CostModel.zeros().vector())))
    rows = []
    for n in args.sizes:
        blocked = rng.random((n, n)) < 0.2
        free = np.flatnonzero(~blocked.ravel())
        goals = rng.choice(free, min(args.goals, len(free)), replace=False)
        graphs = {"highways": highways(blocked), "costmodel": model.guidance(blocked)}
        figures = {"bfs_ms": lambda: per_goal_ms(blocked, None, goals),
                   "bfs_row_ms": lambda: per_goal_ms(blocked, None, goals, "row"),
                   "bfs_search_ms": lambda: search_ms(blocked, None, goals)}
        for name, guidance in graphs.items():
            figures[f"{name}_ms"] = lambda g=guidance: per_goal_ms(blocked, g, goals)
            figures[f"{name}_row_ms"] = lambda g=guidance: per_goal_ms(blocked, g, goals, "row")
            figures[f"{name}_search_ms"] = lambda g=guidance: search_ms(blocked, g, goals)
            figures[f"scipy_{name}_ms"] = lambda g=guidance: scipy_ms(g, goals)
        # every figure once a round, `--repeat` rounds: a burst of load on the shared cores
        # falls on all of them alike, and the median of the rounds is kept
        times = {key: [] for key in figures}
        for _ in range(args.repeat):
            for key, measure in figures.items():
                times[key].append(measure())
        row = {"side": n, **{key: statistics.median(t) for key, t in times.items()}}
        for view in ("", "_row", "_search"):
            row[f"guided{view}_over_bfs"] = (max(row[f"highways{view}_ms"],
                                                 row[f"costmodel{view}_ms"])
                                             / row[f"bfs{view}_ms"])
        rows.append(row)
        print(f"{n}x{n}: a new goal's distances (ms), array / row / search: "
              + "; ".join(f"{label} " + " / ".join(f"{row[f'{key}{view}_ms']:.3f}"
                                                   for view in ("", "_row", "_search"))
                          for label, key in (("BFS", "bfs"), ("highways", "highways"),
                                             ("cost model", "costmodel")))
              + "; guided / BFS " + " / ".join(f"{row[f'guided{view}_over_bfs']:.2f}x"
                                              for view in ("", "_row", "_search"))
              + f"; scipy's Dijkstra {row['scipy_highways_ms']:.3f} highways, "
              f"{row['scipy_costmodel_ms']:.3f} cost model", flush=True)
    ticks = []
    for side, agents in ((21, 64), (128, 2048)):
        blocked = np.random.default_rng(1).random((side, side)) < 0.2
        for name, guidance in (("none", None), ("highways", highways(blocked))):
            ms = tick_ms(blocked, agents, guidance, args.ticks, np.random.default_rng(2))
            ticks.append({"side": side, "agents": agents, "guidance": name, "tick_ms": ms})
            print(f"PIBT tick ({FLEET_RULE}, distance rankings), {side}x{side}, {agents} agents, "
                  f"guidance {name}: {ms:.1f} ms", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"distances": rows, "ticks": ticks}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
