"""The field's yardstick: the project's conflict rules inside POGEMA, on POGEMA's benchmark maps.

    python -m mapf_fleet.evaluation.pogema_bench --family random --agents 64 --instances 32 \\
        --mode lifelong --conflict-rule pibt_anchor_swap --guidance none highways
    python -m mapf_fleet.evaluation.pogema_bench --checkpoint models/default.pt \\
        --guidance congestion models/guidance/online_warehouse_33x33_128.online.json

POGEMA (pogema 1.4.0, `requirements-pogema.txt`; scripts/setup.sh installs it into
<venv>/pogema, which only this module puts on sys.path) is the environment of the learned-MAPF
field's benchmark (pogema-benchmark, ICLR 2025). Each step, the project's coordination layer
computes the joint move (`coordination.factory.make_shield(rule, grid, goals, guidance=...)`)
and POGEMA executes it. The rankings: plain PIBT's (`coordination.plan.distance_rankings`, the
default, `--checkpoint heuristic`), or a checkpoint's (`--checkpoint FILE`: the evaluator's
`CheckpointBatchPolicy` on the observations `evaluation.lifelong.observe_runs` builds from
POGEMA's positions and goals, ranked as `evaluate` ranks it under the rule: the checkpoint's
recorded ranking for the rule, else the rule's default). Online guidance (`congestion`,
`*.online.json`) is stepped as a fleet run steps it (`fleet.run.FleetRun.advance`): the
source's flow observes every tick's moves and hands the shield a new graph every period ticks
(`set_guidance`), and the observations read the same graph. Every step is checked three ways:

- `rule mismatches`: the project's own conflict rules (`grid.env.resolve_moves`, the paper's
  rules that the simulator runs) applied to the same actions give other cells than the shield
  chose (a move they revert: a collision in the project's sense, counted as `collisions`);
- `pogema mismatches`: the cells POGEMA reports after its step differ from the shield's
  (POGEMA's `soft` collision system, the benchmark's, reverts conflicting moves on its own);
- the claim is 0 of both on every step; the table prints them beside each figure.

Lifelong (`on_target="restart"`): POGEMA draws an agent's next goal when it arrives; the new
goals are fed to the shield with `set_goals`. Figure: POGEMA's own `avg_throughput` (goals
reached by all agents / episode steps). One-shot (`on_target="nothing"`, the benchmark's MAPF
setting): success (CSR: all agents on their goals at once within 128 steps).

Maps and published figures (`data/pogema_benchmark/`, Apache-2.0, README.md there): the
benchmark's 128 random maps (17-21 cells a side) and 128 mazes (instance k: map k, seed 0), and
the 33x46 warehouse (instance k: seed k), with the benchmark's episode lengths, collision system
and obstacle padding (obs_radius 5). Published figures are per instance from the benchmark's raw
data: the table averages them over exactly the instances measured here.
The published runs used pogema 1.3.0; 1.4.0 gives the same maps, starts and first goals, but
its lifelong generator draws again when a new goal falls on the agent's own cell (1.3.0 kept
it), so later goal sequences may differ. MAPF-GPT publishes no per-instance data (only plots):
it is not in the table.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapf_fleet.coordination.factory import make_shield
from mapf_fleet.coordination.plan import distance_rankings
from mapf_fleet.coordination.rules import FLEET_RULE, Rule
from mapf_fleet.grid.actions import actions_between
from mapf_fleet.grid.env import resolve_moves
from mapf_fleet.grid.guidance_made import GuidanceSource
from mapf_fleet.models.policy import DEVICE_HELP, device_arg

from .lifelong import observe_runs
from .policies import HEURISTIC, build_policy, parse_policy, with_conflict_rule

POGEMA_VERSION = "1.4.0"
DATA = Path(__file__).resolve().parent / "data" / "pogema_benchmark"
OBS_RADIUS = 5  # the benchmark's padding (pogema-toolbox's Environment default)
COLLISION_SYSTEM = "soft"  # the benchmark's


@dataclass(frozen=True)
class Family:
    maps_file: str
    lifelong_steps: int
    one_shot_steps: int
    instances: int
    single_map: str | None = None  # warehouse: one map, instance k = seed k

    def instance(self, maps: dict, k: int) -> tuple[str, str, int]:
        """(map name, map text, seed) of instance k."""
        if self.single_map:
            return self.single_map, maps[self.single_map], k
        name = sorted(maps)[k]
        return name, maps[name], 0


FAMILIES = {
    "random": Family("random.yaml", 256, 128, 128),
    "mazes": Family("mazes.yaml", 128, 128, 128),
    "warehouse": Family("warehouse.yaml", 256, 128, 128, single_map="wfi_warehouse"),
}
# The headline published figures (64 agents; warehouse 192), means over all 128 instances of
# pogema-benchmark's raw data (commit 3303133, raw_data_LMAPF / raw_data_MAPF); the table
# recomputes each over the instances measured (`published_mean`). Tested against the data file.
PUBLISHED_SOURCE = "pogema-benchmark raw data (github.com/CognitiveAISystems/pogema-benchmark)"
RHCR_RANDOM_64 = 3.819
RHCR_MAZES_64 = 2.587
FOLLOWER_RANDOM_64 = 2.465
MATS_LP_RANDOM_64 = 2.431
FOLLOWER_WAREHOUSE_192 = 3.937
LACAM_MAZES_64_SUCCESS = 0.906


class PogemaMissing(RuntimeError):
    """pogema is not installed where the benchmark looks, or another version is."""


def pogema_dir() -> Path:
    return Path(os.environ.get("MAPF_FLEET_POGEMA_DIR", Path(sys.prefix) / "pogema"))


def import_pogema():
    """The pogema module, from `pogema_dir()` (first on sys.path, so its pydantic 1 and gymnasium
    are the ones it gets); PogemaMissing (one line) when absent or of another version."""
    where = pogema_dir()
    if where.is_dir() and str(where) not in sys.path:
        sys.path.insert(0, str(where))
    try:
        import pogema
    except ImportError as err:
        raise PogemaMissing(f"pogema is not installed in {where} ({err}): run `bash "
                            f"scripts/setup.sh` (it installs requirements-pogema.txt there)") from None
    if pogema.__version__ != POGEMA_VERSION:
        raise PogemaMissing(f"pogema {pogema.__version__} found in {Path(pogema.__file__).parent}; "
                            f"this benchmark is pinned to {POGEMA_VERSION} (requirements-pogema.txt)")
    return pogema


def load_maps(family: str) -> dict:
    import yaml

    return yaml.safe_load((DATA / FAMILIES[family].maps_file).read_text())


def load_published() -> dict:
    return json.loads((DATA / "published.json").read_text())


def published_mean(published: dict, mode: str, family: str, method: str, agents: int,
                   instances) -> tuple[float | None, int]:
    """(the method's published mean over `instances`, how many of them it has): throughput
    (goals / steps) for lifelong, success rate for one-shot."""
    table = published[mode][family]
    values = table["methods"].get(method, {}).get(str(agents))
    if values is None:
        return None, 0
    got = [values[k] for k in instances if values[k] is not None]
    if not got:
        return None, 0
    scale = table["steps"] if mode == "lifelong" else 1
    return float(np.mean(got)) / scale, len(got)


@dataclass
class EpisodeResult:
    figure: float  # lifelong: avg_throughput; one-shot: 1.0 solved / 0.0
    steps: int
    rule_mismatches: int = 0  # agent-steps where resolve_moves disagrees with the shield
    collisions: int = 0  # agent-steps resolve_moves reverts
    pogema_mismatches: int = 0  # agent-steps where POGEMA's cell differs from the shield's
    seconds: float = 0.0  # the tick's own time: shield, rankings (policy), guidance updates
    cpu_seconds: float = 0.0  # the same spans' CPU time (wall time also counts waiting for a core)
    guidance_updates: int = 0  # online guidance: new graphs handed to the shield


def make_env(pogema, mode: str, family: str, map_text: str, map_name: str, seed: int,
             agents: int):
    fam = FAMILIES[family]
    lifelong = mode == "lifelong"
    config = pogema.GridConfig(
        map=map_text, map_name=map_name, seed=seed, num_agents=agents,
        max_episode_steps=fam.lifelong_steps if lifelong else fam.one_shot_steps,
        on_target="restart" if lifelong else "nothing", collision_system=COLLISION_SYSTEM,
        obs_radius=OBS_RADIUS, observation_type="POMAPF")
    return pogema.pogema_v0(grid_config=config)


class Clock:
    """Wall and CPU time of the spans run under `with clock:` (on a loaded machine the wall time
    also counts the waits for a core that other processes hold; the CPU time does not)."""

    def __init__(self):
        self.wall = self.cpu = 0.0

    def __enter__(self):
        self._wall, self._cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall += time.perf_counter() - self._wall
        self.cpu += time.process_time() - self._cpu


class EpisodeView:
    """What `evaluation.lifelong.observe_runs` reads of a run (grid, positions, goals, guidance):
    the episode's state inside POGEMA, so a policy sees the observations the evaluator builds."""

    def __init__(self, grid, positions, goals, guidance):
        self.grid = np.asarray(grid) != 0
        self.positions, self.goals, self.guidance = positions, goals, guidance


def run_episode(pogema, mode: str, family: str, map_name: str, map_text: str, seed: int,
                agents: int, rule: Rule, guidance: GuidanceSource,
                planning_budget: float | None = None, policy=None) -> EpisodeResult:
    """One episode in POGEMA with the shield of `rule` making every move (module docstring).
    policy: None (plain PIBT's distance rankings) or a batch policy of `evaluation.policies`
    (`rank` on the lifelong evaluator's observations, told what was `executed`)."""
    env = make_env(pogema, mode, family, map_text, map_name, seed, agents)
    env.reset(seed=seed)
    grid_obj = env.unwrapped.grid
    grid = grid_obj.get_obstacles(ignore_borders=True).astype(np.uint8)

    def cells(xy) -> np.ndarray:
        return np.asarray(xy, dtype=np.int64).reshape(-1, 2)

    positions = cells(grid_obj.get_agents_xy(ignore_borders=True))
    goals = cells(grid_obj.get_targets_xy(ignore_borders=True))
    clock = Clock()
    with clock:
        graph = guidance.for_map(grid)
        shield = make_shield(rule, grid, goals, planning_budget=planning_budget, guidance=graph)
        flow = guidance.flow(grid)  # online guidance (None: static)
        view = EpisodeView(grid, positions, shield.goals, graph)
        if policy is not None:
            policy.reset(1, agents)
    result = EpisodeResult(figure=0.0, steps=0)
    while True:
        with clock:
            if policy is None:
                rankings = distance_rankings(shield, positions)
            else:
                view.positions, view.goals = positions, shield.goals
                obs = observe_runs([view], policy.observation)
                rankings = policy.rank(obs, positions[None], result.steps)[0]
            step = shield.step(positions, rankings)
            ours = np.asarray(step.positions, dtype=np.int64)
            actions = actions_between(positions, ours)
            if policy is not None:
                policy.executed(actions[None])  # DCC's last action: the executed one
        by_rules, collided = resolve_moves(grid, positions, actions)
        result.rule_mismatches += int((by_rules != ours).any(axis=1).sum())
        result.collisions += int(collided.sum())
        _, _, terminated, truncated, infos = env.step(actions.tolist())
        result.steps += 1
        before, positions = positions, cells(grid_obj.get_agents_xy(ignore_borders=True))
        result.pogema_mismatches += int((positions != ours).any(axis=1).sum())
        if flow is not None:  # as `FleetRun.advance`: the next ticks read the updated costs
            with clock:
                graph = flow.step(before, positions)
                if graph is not None:
                    shield.set_guidance(graph)
                    view.guidance = graph
                    result.guidance_updates += 1
        if all(terminated) or all(truncated):
            metrics = infos[0].get("metrics", {})
            result.figure = float(metrics["avg_throughput"] if mode == "lifelong"
                                  else metrics["CSR"])
            break
        if mode == "lifelong":
            new_goals = cells(grid_obj.get_targets_xy(ignore_borders=True))
            if (new_goals != shield.goals).any():
                with clock:
                    shield.set_goals(new_goals)
    result.seconds, result.cpu_seconds = clock.wall, clock.cpu
    return result


def free_flow_bound(pogema, family: str, map_name: str, map_text: str, seed: int,
                    agents: int) -> float:
    """Lifelong goals per step if every agent walked its goal sequence alone on shortest paths
    (POGEMA's own sequences, `get_lifelong_targets_xy`): no method exceeds it on the episode."""
    from mapf_fleet.grid.heuristic import distance_table

    steps = FAMILIES[family].lifelong_steps
    env = make_env(pogema, "lifelong", family, map_text, map_name, seed, agents)
    env.reset(seed=seed)
    inner = env.unwrapped
    grid = inner.grid.get_obstacles(ignore_borders=True) != 0
    starts = inner.grid.get_agents_xy(ignore_borders=True)
    inner.grid_config.max_episode_steps = 4 * steps  # sequences beyond any walk of `steps`
    sequences = inner.get_lifelong_targets_xy(ignore_borders=True)
    table, w, reached = distance_table(grid), grid.shape[1], 0
    for start, sequence in zip(starts, sequences):
        cell, walked = start[0] * w + start[1], 0
        for r, c in sequence:
            walked += table.row(r * w + c)[cell]
            if walked > steps:
                break
            reached, cell = reached + 1, r * w + c
    return reached / steps


@dataclass
class Row:
    family: str
    mode: str
    agents: int
    rule: str
    guidance: str
    instances: list
    episodes: list = field(default_factory=list)
    policy: str = HEURISTIC  # heuristic: plain PIBT's distance rankings; else a checkpoint's stem
    ranking: str = "distance"  # the ranking the rule arbitrates

    def summary(self) -> dict:
        e = self.episodes
        ticks = sum(r.steps for r in e)
        return {"family": self.family, "mode": self.mode, "agents": self.agents,
                "policy": self.policy, "ranking": self.ranking,
                "rule": self.rule, "guidance": self.guidance, "episodes": len(e),
                "figure": round(float(np.mean([r.figure for r in e])), 4) if e else None,
                "rule_mismatches": sum(r.rule_mismatches for r in e),
                "collisions": sum(r.collisions for r in e),
                "pogema_mismatches": sum(r.pogema_mismatches for r in e),
                "ms_per_tick": round(1000 * sum(r.seconds for r in e) / max(ticks, 1), 2),
                "cpu_ms_per_tick": round(1000 * sum(r.cpu_seconds for r in e) / max(ticks, 1), 2),
                "guidance_updates": sum(r.guidance_updates for r in e)}


PUBLISHED_METHODS = {"lifelong": ("RHCR", "Follower", "MATS-LP"),
                     "one_shot": ("LaCAM", "DCC", "SCRIMP")}


def table(rows: list[Row], published: dict) -> str:
    """Our figures beside the published ones on the same instances."""
    lines = []
    for mode in ("lifelong", "one_shot"):
        mine = [r for r in rows if r.mode == mode]
        if not mine:
            continue
        what = "goals per step" if mode == "lifelong" else "success rate"
        methods = PUBLISHED_METHODS[mode]
        lines.append(f"{mode} ({what}; published: {PUBLISHED_SOURCE}, same instances)")
        lines.append(f"{'family':10} {'agents':>6} {'policy':10} {'rule':22} {'guidance':26} "
                     f"{'n':>4} "
                     f"{'ours':>7} " + " ".join(f"{m:>9}" for m in methods)
                     + f" {'rule mism.':>10} {'pogema mism.':>12} {'ms/tick':>8} {'cpu ms':>7}")
        for r in mine:
            s = r.summary()
            pubs = []
            for m in methods:
                value, count = published_mean(published, mode, r.family, m, r.agents,
                                              r.instances[:len(r.episodes)])
                pubs.append("      n/a" if value is None else
                            f"{value:9.3f}" if count == len(r.episodes) else f"{value:6.3f}/{count:<2}")
            lines.append(f"{r.family:10} {r.agents:>6} {r.policy:10} {r.rule:22} {r.guidance:26} "
                         f"{s['episodes']:>4} {s['figure']:>7.3f} " + " ".join(pubs)
                         + f" {s['rule_mismatches']:>10} {s['pogema_mismatches']:>12} "
                         f"{s['ms_per_tick']:>8.2f} {s['cpu_ms_per_tick']:>7.2f}")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m mapf_fleet.evaluation.pogema_bench",
                                description=__doc__.split("\n")[0])
    p.add_argument("--family", nargs="+", choices=sorted(FAMILIES), default=["random"])
    p.add_argument("--mode", nargs="+", choices=("lifelong", "one_shot"), default=["lifelong"])
    p.add_argument("--agents", nargs="+", type=int, default=[64])
    p.add_argument("--instances", type=int, default=8,
                   help="the first N instances of the family (at most 128)")
    p.add_argument("--first", type=int, default=0, help="the first instance index")
    p.add_argument("--conflict-rule", nargs="+", default=[FLEET_RULE],
                   help="coordinated rules of coordination.rules (revert has no shield); "
                        f"default: the fleet's, {FLEET_RULE}")
    p.add_argument("--checkpoint", nargs="+", default=[HEURISTIC], metavar="C",
                   help="whose rankings the rule arbitrates, one row each: heuristic (plain "
                        "PIBT's distance rankings, the default) or a checkpoint file (its "
                        "recorded ranking for the rule, as `evaluate`)")
    p.add_argument("--device", default="auto", type=device_arg,
                   help=f"torch device of checkpoints: {DEVICE_HELP}")
    p.add_argument("--guidance", nargs="+", default=None,
                   help="none | highways | congestion (online) | MODEL.costmodel.json | "
                        "MODEL.online.json (online) (a guidance file fits one map only); "
                        "default: what `evaluate` runs for the checkpoint and rule (its recorded "
                        "guidance, else the fleet's: what `mapf-fleet up` runs)")
    p.add_argument("--planning-budget", type=float, default=None,
                   help="seconds per re-plan of the lacam rule")
    p.add_argument("--out", type=Path, help="write the rows as JSON here")
    p.add_argument("--free-flow", action="store_true",
                   help="instead: each family's lifelong free-flow bound (`free_flow_bound`) "
                        "beside the published figures")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    prog = "python -m mapf_fleet.evaluation.pogema_bench"
    try:
        if not 1 <= args.instances or args.first < 0 or args.first + args.instances > 128:
            raise ValueError(f"--first {args.first} --instances {args.instances}: the families "
                             f"have 128 instances (0..127)")
        rules = [Rule.parse(r) for r in args.conflict_rule]
        for r in rules:
            if not r.coordinated:
                raise ValueError(f"--conflict-rule {r}: has no shield to make the moves")
        # (checkpoint, rule) -> its spec under the rule; read here, refused before anything runs
        specs = {(c, str(r)): policy_spec(c, r, args.device)
                 for c in dict.fromkeys(args.checkpoint) for r in rules}
        sources_of = guidance_sources(args.guidance, specs)
        pogema = import_pogema()
    except (ValueError, FileNotFoundError, PogemaMissing) as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        return 2
    published = load_published()
    instances = list(range(args.first, args.first + args.instances))
    if args.free_flow:
        for family in args.family:
            maps = load_maps(family)
            for agents in args.agents:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # pogema's own notices
                    bound = np.mean([free_flow_bound(pogema, family, *FAMILIES[family].instance(
                        maps, k), agents) for k in instances])
                pubs = {m: published_mean(published, "lifelong", family, m, agents,
                                          instances)[0] for m in PUBLISHED_METHODS["lifelong"]}
                print(f"{family} {agents}: free-flow bound {bound:.3f} goals per step; "
                      + ", ".join(f"{m} {v:.3f}" for m, v in pubs.items() if v is not None))
        return 0
    rows = []
    for family in args.family:
        maps = load_maps(family)
        for mode in args.mode:
            for agents in args.agents:
                for (checkpoint, rule_name), spec in specs.items():
                    rule = Rule.parse(rule_name)
                    policy = policy_of(spec)
                    for source in sources_of[(checkpoint, rule_name)]:
                        row = Row(family, mode, agents, str(rule), source.label, instances,
                                  policy=spec.kind if policy is None else Path(checkpoint).stem,
                                  ranking=spec.resolved_ranking)
                        for k in instances:
                            name, text, seed = FAMILIES[family].instance(maps, k)
                            with warnings.catch_warnings():
                                warnings.simplefilter("ignore")  # pogema's own notices
                                row.episodes.append(run_episode(
                                    pogema, mode, family, name, text, seed, agents, rule, source,
                                    args.planning_budget, policy))
                        rows.append(row)
                        s = row.summary()
                        print(f"{family} {mode} {agents} {row.policy} {rule} {source.label}: "
                              f"{s['figure']} (rule mismatches {s['rule_mismatches']}, pogema "
                              f"mismatches {s['pogema_mismatches']}, {s['ms_per_tick']} ms/tick, "
                              f"CPU {s['cpu_ms_per_tick']} ms/tick)",
                              flush=True)
    print()
    print(table(rows, published))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"command": " ".join([prog, *map(shlex.quote, argv or
                                                                        sys.argv[1:])]),
                                        "pogema": POGEMA_VERSION,
                                        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ",
                                                              time.gmtime()),
                                        "rows": [r.summary() for r in rows]}, indent=1))
    return 0


def guidance_sources(asked: list[str] | None, specs: dict) -> dict:
    """(checkpoint, rule) -> the `GuidanceSource`s its rows run under: `asked` (`--guidance`),
    else the one `evaluate` gives the spec by default (`PolicySpec.default_guidance`: its
    recorded guidance, else what `mapf-fleet up` runs): one default everywhere."""
    given = None if asked is None else [GuidanceSource.parse(g) for g in asked]
    return {key: given or [GuidanceSource.parse(spec.default_guidance)]
            for key, spec in specs.items()}


def policy_spec(checkpoint: str, rule: Rule, device: str):
    """`--checkpoint`'s value under `rule` as `evaluate` reads it (`policies.parse_policy`,
    `with_conflict_rule`); a planner name is refused (the shield makes every move here)."""
    spec = parse_policy(checkpoint, device=device)
    if spec.is_planner:
        raise ValueError(f"--checkpoint {checkpoint}: a planner has no rankings for the rule "
                         f"(here: heuristic or a checkpoint file; the planning arbiter is "
                         f"--conflict-rule lacam)")
    return with_conflict_rule(spec, rule.name)


def policy_of(spec):
    """The batch policy `run_episode` steps for `spec`: None for the heuristic (plain PIBT's
    distance rankings straight from the shield), else the evaluator's `CheckpointBatchPolicy`."""
    if spec.kind != "checkpoint":
        return None
    import torch

    # one torch thread, as `evaluate --lifelong`: on a shared machine a second thread's barrier
    # waits for a core another process holds
    torch.set_num_threads(1)
    return build_policy(spec)


if __name__ == "__main__":
    raise SystemExit(main())
