"""`mapf-fleet evaluate --lifelong`: lifelong MAPF throughput, POGEMA's protocol, on the fleet core.

    mapf-fleet evaluate --lifelong --steps 256 --checkpoint models/default.pt heuristic \\
        --conflict-rule pibt_anchor --kinds dense --sizes 21 --agents 32 64 --instances 16

Every episode is a `fleet.run.FleetRun` with the lifelong task source (`fleet.tasks`): the same
core the simulator node and the real-robot aggregator run, so a fleet run over ROS and this
rollout make the same moves (tested). On arrival a robot draws its next goal from its own seeded
generator, so every policy of one command gets the same goal sequence per robot. Figures per
scenario: **average throughput** (POGEMA: goals reached by all agents / episode steps), goals per
agent, collisions (reverted moves, the paper's rule) and overridden moves (shields).

Policies: checkpoints and `heuristic` under each `--conflict-rule` (`pibt_anchor` with the heuristic
is plain PIBT; `--conflict-rule lacam` is the planning arbiter, `coordination.plan.PlanKeeper`, with
`--planning-budget` seconds per re-plan), and the centralized reference `lacam`: LaCAM (pymapf) replanned from the current
state whenever a goal changes, with `--planner-time-limit` per call (default 1 s); between goal
changes the robots follow the plan; where a call leaves agents without a plan (time limit), those
agents' moves come from plain PIBT over the same state for that tick (counted as `fallbacks`).
Its figure is what a time-limited centralized planner reaches, not an optimum.

`--workers N` splits each row's episodes among N processes (as the one-shot evaluator does its
chunks; the figures do not depend on it: every episode is its own run and goal stream, seeded by
its index in the row), and a row's `seconds` sums its chunks' rollouts.

Published figures (not measured here) are named constants with their source (`PUBLISHED`) and
printed as such.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
import weakref
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapf_fleet.coordination.rules import CONFLICT_RULES, FLEET_GUIDANCE, REVERT, rule_arg
from mapf_fleet.coordination.ranking import rank_actions, tie_breakers
from mapf_fleet.fleet.arbiter import DEFAULT_CONFLICT_RULE, single_choice_ranking
from mapf_fleet.fleet.record import Decisions
from mapf_fleet.fleet.run import FleetRun
from mapf_fleet.fleet.tasks import LifelongTasks
from mapf_fleet.grid.guidance_made import GuidanceSource
from mapf_fleet.models.policy import DEVICE_HELP, device_arg

from .policies import PolicySpec, parse_policy, unique_names, with_conflict_rule
from .protocol import InstanceSet
from .runner import cached_policy, init_worker, process_pool

# Published lifelong throughputs (goals per step), not measured here: pogema-benchmark's raw data
# for lifelong MAPF (ICLR 2025 release, `raw_data_LMAPF`), and the League of Robot Runners 2023.
PUBLISHED = (
    # (maps, agents, steps, method, throughput, source)
    ("random 17-21 cells a side", 64, 256, "RHCR", 3.82, "pogema-benchmark raw_data_LMAPF"),
    ("random 17-21 cells a side", 64, 256, "Follower", 2.47, "pogema-benchmark raw_data_LMAPF"),
    ("random 17-21 cells a side", 64, 256, "MATS-LP", 2.43, "pogema-benchmark raw_data_LMAPF"),
    ("mazes", 64, 128, "RHCR", 2.59, "pogema-benchmark raw_data_LMAPF"),
    ("mazes", 64, 128, "Follower", 1.61, "pogema-benchmark raw_data_LMAPF"),
    ("warehouse 33x46", 192, 128, "Follower", 3.94, "pogema-benchmark raw_data_LMAPF"),
    ("warehouse 33x46", 192, 128, "RHCR", 1.57, "pogema-benchmark raw_data_LMAPF"),
    ("random-32-32-20", 400, 1000, "League of Robot Runners 2023 winner", 7.4,
     "League of Robot Runners 2023"),
)
KINDS = ("random", "dense", "maze", "rooms", "warehouse")
DEFAULT_SIZES = {"dense": 21, "random": 40, "maze": 40, "rooms": 40, "warehouse": 40}


@dataclass
class LifelongResult:
    policy: str
    scenario: str
    num_agents: int
    steps: int
    goals: list = field(default_factory=list)  # per episode: goals reached
    collisions: list = field(default_factory=list)
    overridden: list = field(default_factory=list)
    fallbacks: int = 0  # lacam: agent-ticks whose move came from PIBT (no plan in time)
    ranking: str | None = None  # the ranking under a coordinated rule (None: planners, revert)
    guidance: str = "none"  # the guidance graph every distance read (`GuidanceSource.label`)
    seconds: float = 0.0

    @property
    def throughput(self) -> float:
        return float(np.mean(self.goals)) / self.steps if self.goals else 0.0

    @property
    def throughput_std(self) -> float:
        return float(np.std(np.asarray(self.goals) / self.steps)) if self.goals else 0.0

    def row(self) -> dict:
        return {"policy": self.policy, "ranking": self.ranking, "guidance": self.guidance,
                "scenario": self.scenario, "agents": self.num_agents,
                "steps": self.steps, "episodes": len(self.goals),
                "throughput": round(self.throughput, 4),
                "throughput_std": round(self.throughput_std, 4),
                "goals_per_agent": round(float(np.mean(self.goals)) / self.num_agents, 3)
                if self.goals else 0.0,
                "collisions": float(np.mean(self.collisions)) if self.collisions else 0.0,
                "overridden": float(np.mean(self.overridden)) if self.overridden else 0.0,
                "fallbacks": self.fallbacks, "seconds": round(self.seconds, 2)}


def lifelong_instances(kind: str, size: int, num_agents: int, count: int, seed: int) -> InstanceSet:
    """`count` instances of a map kind; instance i from the seed sequence (seed, kind, size,
    agents, i): the first goals are the instance's, the rest come from the lifelong source."""
    from mapf_fleet.grid.maps import generate_kind_instance

    code = zlib.crc32(kind.encode())
    made = [generate_kind_instance(kind, size, num_agents,
                                   np.random.default_rng([seed, code, size, num_agents, i]))
            for i in range(count)]
    return InstanceSet.from_instances(made, f"generated {kind} maps (seed {seed})")


def lifelong_runs(instances: InstanceSet, steps: int, rule: str, seed: int,
                  series=("overridden",), planning_budget: float | None = None,
                  guidance=None, first: int = 0) -> list[FleetRun]:
    """One lifelong `FleetRun` per instance; episode k's goal generator is seeded (seed, first +
    k) (`first`: where a chunk of a scenario's episodes begins). guidance: a `GuidanceSource` (or
    a value it parses; None: none), its graph per map."""
    source = GuidanceSource.parse(guidance)
    return [FleetRun(instances.maps[k], instances.starts[k],
                     LifelongTasks(grid=instances.maps[k], seed=episode_seed(seed, first + k)),
                     instances.goals[k], rule=rule, max_steps=steps, series=series,
                     planning_budget=planning_budget, guidance=source.for_map(instances.maps[k]),
                     flow=source.flow(instances.maps[k]))
            for k in range(len(instances))]


def episode_seed(seed: int, k: int) -> int:
    """The lifelong goal seed of episode k (the fleet's `goal_seed` parameter for the same
    stream)."""
    return int(np.random.SeedSequence([int(seed), int(k)]).generate_state(1)[0])


def observe_runs(runs: list[FleetRun], observation: str = "paper") -> np.ndarray:
    """(B, N, C, 9, 9) observations of every run's robots with their current goals (C = 6, 7
    for the "cost_to_go" observation). Each run keeps a `GoalObserver` per observation, so a
    step searches only the goals that are new."""
    return np.stack([_observer(run, observation).observe(run.positions, run.goals)
                     for run in runs]).astype(np.float32, copy=False)


_OBSERVERS: "weakref.WeakKeyDictionary[FleetRun, dict]" = weakref.WeakKeyDictionary()


def _observer(run: FleetRun, observation: str):
    from mapf_fleet.grid.goal_observer import GoalObserver

    mine = _OBSERVERS.setdefault(run, {})
    found = mine.get(observation)
    if found is None or found.guidance is not run.guidance:  # online guidance: a new graph
        found = mine[observation] = GoalObserver(run.grid, observation=observation,
                                                 guidance=run.guidance)
    return found


def rollout(policy, runs: list[FleetRun], shielded: bool) -> None:
    """Step the batch policy and the runs together until every run reaches its tick limit:
    under a shield the policy ranks (`policy.rank`) and learns what was executed
    (`policy.executed`); unshielded its first choices go to the paper's rule."""
    n = runs[0].num_robots
    policy.reset(len(runs), n)
    observation = getattr(policy, "observation", "paper")
    while not all(run.finished() for run in runs):
        obs = observe_runs(runs, observation)
        positions = np.stack([run.positions for run in runs])
        tick = runs[0].tick
        if shielded:
            prefs = policy.rank(obs, positions, tick)
        else:
            actions = np.asarray(policy.act(obs, positions))
            prefs = np.array([[single_choice_ranking(a) for a in row] for row in actions])
        executed = []
        for k, run in enumerate(runs):
            result, _ = run.step(Decisions.complete(tick, prefs[k]))
            executed.append(result.actions)
        if shielded:
            policy.executed(np.stack(executed))


def lacam_rollout(runs: list[FleetRun], time_limit: float, seed: int = 0) -> int:
    """The centralized reference: LaCAM from the current state to the current goals, replanned
    whenever a goal changes (or the plan runs out), its next joint move arbitrated by the run's
    rule (a valid plan passes unchanged); agents LaCAM left unplanned take plain PIBT's move.
    Returns the agent-ticks that needed the fallback."""
    from mapf_fleet.coordination.planners import ClassicalPlanner
    from mapf_fleet.grid.actions import ACTION_DELTAS

    planner = ClassicalPlanner("lacam", time_limit, seed)
    fallbacks = 0
    for run in runs:
        plan, at, planned_goals = None, 0, None
        while not run.finished():
            if plan is None or at + 1 >= len(plan) or not np.array_equal(planned_goals, run.goals):
                result = planner.plan(run.grid, run.positions, run.goals)
                plan = None if result.positions is None else np.asarray(result.positions)
                at, planned_goals = 0, run.goals.copy()
            distance = _distance_rankings(run)
            prefs = distance.copy()
            if plan is not None and at + 1 < len(plan):
                nxt = plan[at + 1]
                delta = nxt - run.positions
                for i in range(run.num_robots):
                    hit = np.flatnonzero((ACTION_DELTAS == delta[i]).all(axis=1))
                    if len(hit) and (plan[at] == run.positions).all():
                        a = int(hit[0])
                        prefs[i] = [a] + [x for x in distance[i] if x != a]
                    else:
                        fallbacks += 1
            else:
                fallbacks += run.num_robots
            run.step(Decisions.complete(run.tick, prefs))
            at += 1
            if not (plan is not None and at < len(plan) and (plan[at] == run.positions).all()):
                plan = None  # off the plan (an agent was pushed): replan next tick
    return fallbacks


def _distance_rankings(run: FleetRun) -> np.ndarray:
    obs = observe_runs([run])
    return rank_actions(obs, mode="distance",
                        ties=tie_breakers(np.arange(run.num_robots), run.tick)[None])[0]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mapf-fleet evaluate --lifelong",
                                description=__doc__.split("\n")[0])
    p.add_argument("--lifelong", action="store_true", required=True,
                   help="lifelong MAPF: a new goal on arrival, throughput over --steps")
    p.add_argument("--checkpoint", nargs="+", default=["heuristic"], metavar="C",
                   help="checkpoint files, `heuristic` and/or `lacam` (default: heuristic)")
    p.add_argument("--conflict-rule", nargs="+", default=[DEFAULT_CONFLICT_RULE],
                   type=rule_arg, metavar="RULE",
                   help="conflict rule(s) for decentralized policies, one row each: "
                        f"{', '.join(CONFLICT_RULES)} (default: {DEFAULT_CONFLICT_RULE}, the "
                        "fleet's default; revert = the paper's rule; deprecated: --shield)")
    p.add_argument("--ranking", default=None, metavar="RANKING",
                   help="ranking of checkpoints under the conflict rule (default: the "
                        "evaluator's; deprecated: --preferences)")
    p.add_argument("--kinds", nargs="+", default=["dense"], choices=list(KINDS),
                   help="map kinds (default: dense, the small random maps of 17-21 cells)")
    p.add_argument("--map", nargs="+", default=[], metavar="MAP",
                   help="MovingAI .map files instead of --kinds (starts and first goals drawn "
                        "from --seed)")
    p.add_argument("--sizes", nargs="+", type=int,
                   help=f"map sides per kind (default: {DEFAULT_SIZES})")
    p.add_argument("--agents", nargs="+", type=int, default=[64], help="agent counts (default 64)")
    p.add_argument("--instances", type=int, default=16, help="episodes per scenario (default 16)")
    p.add_argument("--steps", type=int, default=256, help="episode length in steps (default 256)")
    p.add_argument("--seed", type=int, default=0, help="seed of maps, starts and goal streams")
    p.add_argument("--guidance", nargs="+", default=None, type=_guidance_arg, metavar="G",
                   help="guidance graph(s) every distance reads, one row each: none, highways "
                        "(hand-made crisscross lanes), a guidance file (*.guidance.npz, --map "
                        "with one map), a cost model (*.costmodel.json, any map), online "
                        "congestion costs (congestion) or an online learned model "
                        "(*.online.json, any map) "
                        "(default: a checkpoint's recorded guidance, else the fleet's, "
                        f"{FLEET_GUIDANCE}, what `mapf-fleet up` runs; none under revert and "
                        "for lacam)")
    p.add_argument("--planner-time-limit", type=float, default=1.0,
                   help="lacam: seconds per replanning call (default 1)")
    p.add_argument("--planning-budget", type=float, metavar="S",
                   help="--conflict-rule lacam: seconds per re-plan (default 1)")
    p.add_argument("--device", default="auto", type=device_arg,
                   help=f"torch device of learned policies: {DEVICE_HELP}")
    p.add_argument("--workers", type=int, default=1,
                   help="rollout processes: each row's episodes split among them (default 1: "
                        "this process; the figures do not depend on it)")
    p.add_argument("--json", metavar="OUT")
    p.add_argument("--csv", metavar="OUT")
    p.add_argument("--markdown", metavar="OUT")
    p.add_argument("--quiet", action="store_true")
    return p


def _guidance_arg(value: str) -> GuidanceSource:
    try:
        return GuidanceSource.parse(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def scenarios(args) -> list[tuple[str, InstanceSet]]:
    out = []
    if args.map:
        from mapf_fleet.grid.maps import place_agents
        from mapf_fleet.grid.movingai import read_map

        for path in args.map:
            grid = read_map(path)
            for n in args.agents:
                made = [place_agents(grid, n, np.random.default_rng([args.seed, n, i]))
                        for i in range(args.instances)]
                out.append((f"{Path(path).stem} {n}",
                            InstanceSet.from_instances(made, f"MovingAI {Path(path).name}")))
        return out
    for kind in args.kinds:
        for size in args.sizes or [DEFAULT_SIZES[kind]]:
            for n in args.agents:
                out.append((f"{kind} {size}x{size} {n}",
                            lifelong_instances(kind, size, n, args.instances, args.seed)))
    return out


@dataclass(frozen=True)
class LifelongJob:
    """A chunk of one row's episodes (picklable: it runs in this process or a worker's)."""

    spec: PolicySpec
    rule: str  # the rule the runs step under
    instances: InstanceSet  # the chunk's episodes
    first: int  # the chunk's first episode in the row (its goal streams' seeds)
    steps: int
    seed: int
    guidance: GuidanceSource
    planning_budget: float | None
    planner_time_limit: float


def run_lifelong_job(job: LifelongJob) -> dict:
    """The chunk's per-episode goals, collisions and overridden moves, lacam's fallbacks and the
    rollout's seconds."""
    began = time.perf_counter()
    planner = job.spec.is_planner
    # a plan's moves are conflict-free: plain PIBT passes them unchanged (the anchor would put the
    # top agent on its distance order instead of its plan)
    runs = lifelong_runs(job.instances, job.steps, "pibt" if planner else job.rule, job.seed,
                         planning_budget=job.planning_budget, guidance=job.guidance,
                         first=job.first)
    fallbacks = 0
    if planner:
        fallbacks = lacam_rollout(runs, job.planner_time_limit)
    else:
        rollout(cached_policy(job.spec), runs, shielded=job.rule != REVERT)
    return {"goals": [run.goals_reached for run in runs],
            "collisions": [run.recorder.collisions for run in runs],
            "overridden": [run.recorder.overridden for run in runs], "fallbacks": fallbacks,
            "seconds": time.perf_counter() - began}


def evaluate_lifelong(args) -> list[LifelongResult]:
    """Every row (policy, rule, guidance, scenario) of the command, its episodes in chunks run
    in this process (`--workers 1`) or on `--workers` processes (one chunk a process and row);
    the figures do not depend on the split (each episode is its own run and goal stream)."""
    # one torch thread: on a shared machine a second thread's barrier waits for a core another
    # process holds, and a step takes many times longer (docs/results.md, "Performance (2-core
    # machine, no GPU)"); every worker is set up the same way
    init_worker()
    rows = []  # (result, its chunks)
    for name in dict.fromkeys(args.checkpoint):
        base = parse_policy(name, device=args.device,
                            planner_time_limit=args.planner_time_limit)
        rules = ([args.conflict_rule[0]] if base.is_planner
                 else list(dict.fromkeys(args.conflict_rule)))
        for rule in rules:
            spec = base if base.is_planner else with_conflict_rule(base, rule, args.ranking)
            spec = unique_names([spec])[0]
            if not base.is_planner:
                cached_policy(spec)  # a bad checkpoint refused here, before any rollout
            # not given: the spec's own (`PolicySpec.default_guidance`: the checkpoint's recorded
            # guidance, else the fleet's, as `up` runs it)
            given = args.guidance if args.guidance is not None else [spec.default_guidance]
            for guidance in dict.fromkeys(map(GuidanceSource.parse, given)):
                for label, instances in scenarios(args):
                    result = LifelongResult(spec.name, label.rsplit(" ", 1)[0],
                                            instances.starts.shape[1], args.steps,
                                            guidance=guidance.label)
                    if not base.is_planner and rule != REVERT:
                        result.ranking = spec.resolved_ranking
                    splits = np.array_split(np.arange(len(instances)),
                                            min(args.workers, len(instances)))
                    rows.append((result, [LifelongJob(
                        spec, rule, instances.subset(index), int(index[0]), args.steps,
                        args.seed, guidance, args.planning_budget, args.planner_time_limit)
                        for index in splits]))
    if args.workers == 1:
        outputs = (map(run_lifelong_job, chunks) for _, chunks in rows)
        return [_finish(result, chunks, args) for (result, _), chunks in zip(rows, outputs)]
    with process_pool(args.workers) as pool:
        futures = [[pool.submit(run_lifelong_job, job) for job in chunks] for _, chunks in rows]
        return [_finish(result, (f.result() for f in mine), args)
                for (result, _), mine in zip(rows, futures)]


def _finish(result: LifelongResult, outputs, args) -> LifelongResult:
    """The row from its chunks' outputs, in episode order; printed unless --quiet."""
    for out in outputs:
        result.goals += out["goals"]
        result.collisions += out["collisions"]
        result.overridden += out["overridden"]
        result.fallbacks += out["fallbacks"]
        result.seconds += out["seconds"]  # rollout seconds, summed over the chunks
    if not args.quiet:
        row = result.row()
        print(f"[lifelong] {row['policy']} ({result.guidance} guidance) on {row['scenario']} "
              f"{row['agents']}: throughput {row['throughput']:.3f} ({row['seconds']:.1f} s)",
              file=sys.stderr, flush=True)
    return result


def markdown(results: list[LifelongResult]) -> str:
    lines = ["| policy | ranking | guidance | maps | agents | steps | episodes | throughput "
             "(goals/step) | goals per agent | collisions | overridden |",
             "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        row = r.row()
        lines.append(f"| {row['policy']} | {row['ranking'] or '-'} | {row['guidance']} "
                     f"| {row['scenario']} "
                     f"| {row['agents']} | {row['steps']} "
                     f"| {row['episodes']} | {row['throughput']:.3f} ± {row['throughput_std']:.3f}"
                     f" | {row['goals_per_agent']:.2f} | {row['collisions']:.1f} | "
                     f"{row['overridden']:.1f} |")
    lines += ["", "Published (not measured here; named constants of "
              "`mapf_fleet.evaluation.lifelong.PUBLISHED`):", "",
              "| maps | agents | steps | method | throughput | source |", "|---|---:|---:|---|---:|---|"]
    lines += [f"| {m} | {n} | {t} | {meth} | {v} | {src} |" for m, n, t, meth, v, src in PUBLISHED]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if args.steps < 1 or args.instances < 1 or min(args.agents) < 1 or args.workers < 1:
        print("mapf-fleet evaluate --lifelong: --steps, --instances, --agents and --workers "
              "must be positive", file=sys.stderr)
        return 2
    try:
        results = evaluate_lifelong(args)
    except (FileNotFoundError, ValueError) as exc:
        print(f"mapf-fleet evaluate --lifelong: {exc}", file=sys.stderr)
        return 2
    text = markdown(results)
    print(text)
    meta = {"command": shlex.join(["mapf-fleet", "evaluate", *argv]),
            "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "seed": args.seed,
            "published": [dict(zip(("maps", "agents", "steps", "method", "throughput", "source"),
                                   p)) for p in PUBLISHED]}
    if args.json:
        from mapf_fleet.files import atomic_write

        atomic_write(args.json, json.dumps({"metadata": meta,
                                            "results": [r.row() | {"goals": r.goals}
                                                        for r in results]}, indent=1).encode())
    if args.csv:
        import csv
        import io

        buf = io.StringIO()
        rows = [r.row() for r in results]
        writer = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else ["policy"])
        writer.writeheader()
        writer.writerows(rows)
        Path(args.csv).write_text(buf.getvalue())
    if args.markdown:
        Path(args.markdown).write_text(f"# Lifelong evaluation\n\n`{meta['command']}`\n\n{text}")
    return 0
