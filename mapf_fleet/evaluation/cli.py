"""`mapf-fleet evaluate`: the paper's evaluation protocol for checkpoints and references.

    mapf-fleet evaluate --checkpoint models/dhc.pt [more.pt ...] [--sizes 40] [--agents 4 8]
        [--instances 200] [--workers 2] [--json out.json] [--csv out.csv]
        [--markdown out.md] [--plot out.png]
    mapf-fleet evaluate --checkpoint heuristic --map F.map --scen a.scen b.scen --agents 32
    mapf-fleet evaluate --checkpoint heuristic --map a.map b.map --scen a.scen b.scen --agents 32
    mapf-fleet evaluate --checkpoint heuristic --map maps/ --scen scens/ --agents 32
    mapf-fleet evaluate --lifelong --steps 256 --checkpoint F.pt heuristic --kinds dense
        (lifelong throughput; `mapf-fleet evaluate --lifelong --help`)

The references of the protocol file (the heuristic policy and LaCAM) are added to the tables
unless --no-references. Prints the paper-layout tables (success rate, average steps) per map.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import platform
import shlex
import sys
import time
from pathlib import Path

from mapf_fleet.grid.maps import DENSE
from mapf_fleet.version import code_version

from mapf_fleet.aliases import renamed_options
from mapf_fleet.coordination.rules import FLEET_GUIDANCE, FLEET_RULE, REVERT, rule_arg
from mapf_fleet.coordination.ranking import DEFAULT_RANKING_BY_RULE, RANKINGS
from mapf_fleet.models.policy import DEVICE_HELP, device_arg

from .policies import REFERENCE_NAMES, parse_policy, unique_names, with_conflict_rule, with_guidance
from .protocol import (
    DEFAULT_CACHE,
    DEFAULT_CONFIG,
    DEFAULT_TESTSETS,
    ProtocolConfig,
    ProtocolError,
    FAMILY_AGENTS,
    FAMILY_KINDS,
    FAMILY_SIZES,
    family_scenarios,
    movingai_pairs,
    movingai_scenarios,
    protocol_scenarios,
    scenario_instances,
)

# Default limit for MovingAI maps: the protocol's limit of the nearest protocol map size.
SMALL_MAP_LIMIT, LARGE_MAP_LIMIT = 256, 386


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mapf-fleet evaluate", description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", nargs="*", default=[], metavar="C",
                   help=f"checkpoint files, or the pseudo-checkpoints {', '.join(REFERENCE_NAMES)}")
    p.add_argument("--no-references", action="store_true", help="do not add the protocol's references")
    p.add_argument("--conflict-rule", nargs="+", default=[FLEET_RULE], type=rule_arg,
                   metavar="RULE",
                   help="coordination of decentralized policies: revert (the paper's rule: "
                        "conflicting moves are reverted) and/or pibt (CS-PIBT over each agent's "
                        "ranked actions) and/or pibt_anchor (the same, the top-priority agent on "
                        "its distance order), their _swap / _hindrance variants "
                        "(docs/coordination.md) and/or lacam (a kept LaCAM plan over the "
                        "rankings, --planning-budget per re-plan); several give one row each "
                        f"(default: {FLEET_RULE}, what `mapf-fleet up` runs; revert for the "
                        "paper's protocol; deprecated: --shield, none)")
    p.add_argument("--ranking", nargs="+", choices=list(RANKINGS), metavar="RANKING",
                   help=f"how a policy ranks its actions under the conflict rule, one row each: "
                        f"{', '.join(RANKINGS)} (default: for a checkpoint the ranking "
                        f"it records for the rule (metadata rankings, e.g. a DAgger round's), "
                        f"else the rule's: "
                        + ", ".join(f"{m} under {r}" for r, m in DEFAULT_RANKING_BY_RULE.items())
                        + "; an _epibt or _lns rule its base rule's; distance for the "
                          "heuristic; deprecated: --preferences)")
    p.add_argument("--guidance", nargs="+", default=None, metavar="G",
                   help="guidance graph(s) the observations and the conflict rule read, one row "
                        "each: none, highways (hand-made crisscross lanes), a guidance file "
                        "(*.guidance.npz, one map) or a cost model (*.costmodel.json) "
                        "(default: a checkpoint's recorded guidance, the one it was trained to "
                        f"read; else the fleet's, {FLEET_GUIDANCE}, what `mapf-fleet up` runs, "
                        "and none under revert, the paper's protocol; none: BFS distances, the "
                        "unguided world)")
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="protocol YAML (default %(default)s)")
    p.add_argument("--sizes", nargs="+", type=int, help="map sizes to run (default: all of the protocol)")
    p.add_argument("--agents", nargs="+", type=int, help="agent counts to run (with --map: exactly one)")
    p.add_argument("--instances", type=int, help="instances per scenario (default: the protocol's 200)")
    p.add_argument("--seed", type=int, help="seed of generated instances (default: the protocol's)")
    p.add_argument("--testsets", default=str(DEFAULT_TESTSETS), help="folder of the published DHC test sets")
    p.add_argument("--cache-dir", default=str(DEFAULT_CACHE), help="cache of generated instances")
    p.add_argument("--map", nargs="+", default=[], metavar="MAP",
                   help="MovingAI .map files or folders of them (instead of the protocol)")
    p.add_argument("--scen", nargs="+", default=[], metavar="SCEN",
                   help="MovingAI .scen files or folders, one instance each: with one map, all "
                        "of them; with several, in --map order (as many as maps), else each "
                        "with the map its lines name")
    p.add_argument("--kinds", nargs="+", choices=[*FAMILY_KINDS, DENSE], metavar="KIND",
                   help=f"structured map families instead of the protocol's random maps: "
                        f"{', '.join(FAMILY_KINDS)}; generated from --seed, sides from --sizes "
                        f"(default {' '.join(map(str, FAMILY_SIZES))}), counts from --agents "
                        f"(default {' '.join(map(str, FAMILY_AGENTS))}), the protocol's step limit "
                        f"of that side. {DENSE}: the small crowded random maps (side drawn from "
                        f"S-4..S for --sizes S, default {DENSE_SIZE}; agents default "
                        f"{' '.join(map(str, DENSE_AGENTS))}; {DENSE_STEPS} steps unless "
                        f"--max-steps)")
    p.add_argument("--max-steps", type=int, help=f"step limit for --map (default {SMALL_MAP_LIMIT} up to 40x40, else {LARGE_MAP_LIMIT})")
    p.add_argument("--workers", type=int, default=1, help="parallel processes")
    p.add_argument("--batch-size", type=int, default=200, help="episodes stepped together per job")
    p.add_argument("--device", default="auto", type=device_arg,
                   help=f"torch device of learned policies: {DEVICE_HELP}")
    p.add_argument("--planner-time-limit", type=float, help="seconds of planning per instance")
    p.add_argument("--planning-budget", type=float, metavar="S",
                   help="--conflict-rule lacam: seconds of planning per re-plan, one tick's budget "
                        "(default 1)")
    p.add_argument("--json", metavar="OUT", help="write every figure (and every episode) as JSON")
    p.add_argument("--csv", metavar="OUT", help="write one row per policy and scenario")
    p.add_argument("--markdown", metavar="OUT", help="write the tables, with the extra metrics")
    p.add_argument("--plot", metavar="OUT.png", help="plot success rate against agent count")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return p


def _scenarios(args, config: ProtocolConfig):
    """[(Scenario, InstanceSet)] from the protocol or from MovingAI files."""
    if args.map and args.kinds:
        raise ProtocolError("--kinds and --map are two different sources of maps: give one")
    if args.map:
        if not args.agents or len(args.agents) != 1:
            raise ProtocolError("--map needs exactly one --agents N")
        from mapf_fleet.grid.movingai import read_map

        out = []
        for map_path, scen_paths in movingai_pairs(args.map, args.scen):
            grid = read_map(map_path)
            limit = args.max_steps or (SMALL_MAP_LIMIT if max(grid.shape) <= 40 else LARGE_MAP_LIMIT)
            scenario, instances = movingai_scenarios(map_path, scen_paths, args.agents[0], limit)
            if args.instances:
                instances = instances.subset(slice(0, args.instances))
            out.append((scenario, instances))
        return out
    if args.scen:
        raise ProtocolError("--scen needs --map")
    count = args.instances or config.instances
    seed = config.seed if args.seed is None else args.seed
    if args.kinds:
        families = [k for k in args.kinds if k != DENSE]
        out = family_scenarios(config, families, count, seed, args.sizes, args.agents,
                               args.max_steps) if families else []
        if DENSE in args.kinds:
            out += dense_scenarios(count, seed, args.sizes, args.agents, args.max_steps)
        return out
    out = []
    for scenario in protocol_scenarios(config, args.sizes, args.agents):
        if args.max_steps:
            from dataclasses import replace

            scenario = replace(scenario, max_steps=args.max_steps)
        instances = scenario_instances(scenario, count, density=config.density, seed=seed,
                                       testsets_dir=args.testsets, cache_dir=args.cache_dir)
        if "is absent" in instances.source:
            print(f"mapf-fleet evaluate: {scenario.key}: {instances.source.split('; ', 1)[1]}: "
                  f"using generated instances (not the paper's; --testsets DIR names the folder)",
                  file=sys.stderr)
        out.append((scenario, instances))
    return out


# the small dense random maps learned MAPF is compared on (grid.maps.DENSE: 17-21 cells a side)
DENSE_SIZE, DENSE_AGENTS, DENSE_STEPS = 21, (32, 48, 64), 128


def dense_scenarios(count: int, seed: int, sizes=None, agents=None, max_steps=None):
    """One scenario per (largest side, agent count) of `grid.maps.DENSE` instances; instance i
    from the seed sequence (seed, "dense", side, agents, i), so any prefix is the same."""
    import zlib

    import numpy as np

    from mapf_fleet.grid.maps import capacity, generate_kind_instance

    from .protocol import InstanceSet, Scenario

    code = zlib.crc32(DENSE.encode())
    out = []
    for size in sizes or [DENSE_SIZE]:
        for n in agents or DENSE_AGENTS:
            if n > capacity(DENSE, size):
                raise ProtocolError(f"--kinds {DENSE}: {n} agents do not fit every map of "
                                    f"side {size - 4}..{size} (at most {capacity(DENSE, size)})")
            made = [generate_kind_instance(DENSE, size, n,
                                           np.random.default_rng([seed, code, size, n, i]))
                    for i in range(count)]
            out.append((Scenario(f"{DENSE} {size - 4}-{size}", n, max_steps or DENSE_STEPS),
                        InstanceSet.from_instances(made, f"generated {DENSE} maps (seed {seed})")))
    return out


def _sha256(path: str) -> str:
    # lets a model card tell whether the file it describes is the file that was evaluated
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _metadata(args, config: ProtocolConfig, specs, wall_time: float) -> dict:
    import numpy

    versions = {"python": platform.python_version(), "numpy": numpy.__version__}
    for module in ("torch", "pymapf"):
        try:
            versions[module] = __import__(module).__version__
        except Exception:  # noqa: BLE001 - an absent optional library is just not listed
            pass
    return {
        "command": shlex.join(["mapf-fleet", "evaluate", *args.argv]),
        "protocol_file": args.config,
        "density": config.density,
        "seed": config.seed if args.seed is None else args.seed,
        "policies": [{"name": s.name, "kind": s.kind, "path": s.path, "algorithm": s.algorithm,
                      "conflict_rule": s.conflict_rule,
                      "ranking": (s.resolved_ranking if s.conflict_rule != REVERT
                                  and not s.is_planner else None),
                      "sha256": _sha256(s.path) if s.path else None} for s in specs],
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "code_version": code_version(),
        "workers": args.workers,
        "wall_time_s": round(wall_time, 3),
        "versions": versions,
        "cpu_count": os.cpu_count(),
    }


def main(argv: list[str] | None = None) -> int:
    argv = renamed_options(list(sys.argv[1:] if argv is None else argv), "mapf-fleet evaluate")
    if "--lifelong" in argv:  # lifelong MAPF throughput on the fleet core: its own options
        from .lifelong import main as lifelong_main

        return lifelong_main(argv)
    args = build_parser().parse_args(argv)
    args.argv = argv
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    try:
        config = ProtocolConfig.from_yaml(args.config)
        time_limit = args.planner_time_limit or config.planner_time_limit
        names = list(args.checkpoint)
        if not args.no_references:
            names += [r for r in config.references if r not in names]
        if not names:
            raise ProtocolError("nothing to evaluate: give --checkpoint or drop --no-references")
        base = [parse_policy(n, device=args.device, planner_time_limit=time_limit,
                             planner_seed=config.planner_seed) for n in names]
        specs = []
        for spec in base:
            for rule in dict.fromkeys(args.conflict_rule):
                if spec.is_planner and rule != args.conflict_rule[0]:
                    continue  # a centralized plan is conflict-free: one row
                rankings = [None] if rule == REVERT or not args.ranking else args.ranking
                for ranking in rankings:
                    if spec.kind == "heuristic" and ranking not in (None, "distance"):
                        continue  # no Q-values to rank by
                    specs.append(with_conflict_rule(spec, rule, ranking))
        if args.planning_budget is not None:
            if not args.planning_budget > 0:
                raise ValueError(f"--planning-budget must be a positive number of seconds, "
                                 f"got {args.planning_budget}")
            from dataclasses import replace

            specs = [replace(s, planning_budget=args.planning_budget)
                     if s.conflict_rule == "lacam" else s for s in specs]
        specs = with_guidance(specs, args.guidance)
        specs = unique_names(specs)
        scenarios = _scenarios(args, config)
    except (ProtocolError, FileNotFoundError, ValueError) as exc:
        print(f"mapf-fleet evaluate: {exc}", file=sys.stderr)
        return 2

    from .report import csv_report, markdown_report, plot_success, write_json
    from .runner import evaluate

    def progress(done, total, job):
        if not args.quiet:
            print(f"[{done}/{total}] {job.spec.name} on {job.scenario.key} ({len(job.instances)} episodes)",
                  file=sys.stderr, flush=True)

    began = time.perf_counter()
    results = evaluate(specs, scenarios, workers=args.workers, batch_size=args.batch_size, progress=progress)
    wall_time = time.perf_counter() - began

    coordinated = any(s.conflict_rule != REVERT for s in specs)
    print(markdown_report(results, extra=("agent_success_rate",)
                          + (("collisions", "overrides") if coordinated else ())))
    planners = [r for r in results if r.plan_time is not None]
    if planners:
        from mapf_fleet.coordination.planners import library_version

        print(f"Planner reference: {library_version()}; planning time per instance "
              + ", ".join(f"{r.scenario.key} {r.plan_time / r.summary.episodes:.3f} s" for r in planners if r.summary.episodes))
    print(f"Wall time: {wall_time:.1f} s with {args.workers} worker(s).")

    metadata = _metadata(args, config, specs, wall_time)
    if args.json:
        write_json(args.json, results, metadata)
    if args.csv:
        Path(args.csv).write_text(csv_report(results))
    if args.markdown:
        Path(args.markdown).write_text(
            f"# Evaluation\n\n`{metadata['command']}`\n\n" + markdown_report(results, extra=True)
            + f"\nWall time {wall_time:.1f} s, {args.workers} worker(s).\n"
        )
    if args.plot:
        plot_success(results, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
