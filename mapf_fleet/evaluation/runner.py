"""Runs policies over scenarios: batched episodes in-process, and `workers` processes in parallel.

Decentralized policies step all episodes of a chunk together (one `act` call on
(B, N, C, 9, 9) per step, the channels of the policy's `observation`); finished episodes are
frozen and only the live ones advance.
Planners plan each instance and their plans are replayed through the same environment, so
every policy is measured by the same conflict rules and the same `EpisodeTracker`.

Results do not depend on `workers` or `batch_size`: each episode is independent and the
chunks are put back in instance order.
"""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from .metrics import EpisodeRecord, EpisodeTracker, ScenarioSummary, summarize
from .policies import PolicySpec, build_policy
from .protocol import InstanceSet, Scenario


@dataclass
class ScenarioResult:
    """One cell of the tables: a policy on a scenario."""

    policy: str
    scenario: Scenario
    source: str
    episodes: list[EpisodeRecord]
    compute_time: float  # seconds spent in the episodes (summed over workers)
    plan_time: float | None = None  # planners: seconds of planning, summed over instances
    plan_failures: int = 0  # planners: instances where some agents got no plan in the time budget
    summary: ScenarioSummary = field(init=False)

    def __post_init__(self):
        self.summary = summarize(self.episodes)


def lower_bounds(instances: InstanceSet) -> np.ndarray:
    """(K,) longest single-agent shortest path of each instance (see metrics)."""
    from mapf_fleet.grid.heuristic import bfs_distances_many

    bounds = np.zeros(len(instances), dtype=np.int64)
    for k in range(len(instances)):
        dist = bfs_distances_many(instances.maps[k], instances.goals[k])  # (N, H, W), to each goal
        starts = instances.starts[k]
        d = dist[np.arange(len(starts)), starts[:, 0], starts[:, 1]]
        if (d < 0).any():
            i = int(np.argmax(d < 0))
            raise ValueError(f"instance {k}: agent {i} cannot reach its goal {tuple(instances.goals[k][i])} from {tuple(starts[i])}")
        bounds[k] = d.max()
    return bounds


def _make_env(instances: InstanceSet, k: int, max_steps: int, observation: str = "paper",
              guidance: str = "none"):
    from mapf_fleet.grid.env import EnvConfig, MAPFEnv

    return MAPFEnv(instances.instance(k), EnvConfig(max_steps=max_steps, observation=observation,
                                                    guidance=str(guidance)))


def run_decentralized(policy, instances: InstanceSet, max_steps: int, conflict_rule: str = "revert",
                      planning_budget: float | None = None, stats: list | None = None,
                      guidance: str = "none") -> list[EpisodeRecord]:
    """Step all episodes of `instances` together with a batch policy (reset/act[/keep]).

    Only live episodes are passed to `act`; when some end, `policy.keep(rows)` (if the policy
    has it) drops their recurrent state so the batch shrinks with them.

    conflict_rule "revert": the paper's environment on the policy's `act`; "pibt" / "pibt_anchor"
    (and their variants): each step the policy ranks its five actions per agent
    (`policy.rank`), one `PIBTShield` per episode turns the rankings into conflict-free moves,
    those are executed (and reported back with `policy.executed`), and the overridden
    agent-steps are counted. "lacam": the planning arbiter (`coordination.plan.PlanKeeper`)
    with `planning_budget` seconds per re-plan; its counters (`PlanKeeper.stats`) are appended
    to `stats` when given, one dict per episode. guidance: the guidance graph (a
    `GuidanceSource` spelling) the observations and the rule read, per map."""
    bounds = lower_bounds(instances)
    observation = getattr(policy, "observation", "paper")
    envs = [_make_env(instances, k, max_steps, observation, guidance)
            for k in range(len(instances))]
    obs = np.stack([env.reset() for env in envs]).astype(np.float32)
    positions = np.stack([np.asarray(env.positions) for env in envs])
    trackers = [EpisodeTracker(positions[k], instances.goals[k], max_steps, bounds[k]) for k in range(len(envs))]
    from mapf_fleet.coordination.factory import make_shield
    from mapf_fleet.coordination.rules import Rule

    rule = Rule.parse(conflict_rule, "conflict_rule")
    shields = None if not rule.coordinated else [
        make_shield(conflict_rule, instances.maps[k], instances.goals[k], planning_budget=planning_budget,
                    guidance=envs[k].guidance)
        for k in range(len(envs))]
    policy.reset(len(envs), instances.starts.shape[1])
    live = list(range(len(envs)))
    keep = getattr(policy, "keep", None)

    def shrink(live):
        rows = [j for j, k in enumerate(live) if not trackers[k].done]
        if len(rows) < len(live) and rows and keep is not None:
            keep(rows)
        return [live[j] for j in rows]

    live = shrink(live)
    tick = 0
    while live:
        overridden = None
        if shields is None:
            actions = np.asarray(policy.act(obs[live], positions[live]))
        else:
            rankings = policy.rank(obs[live], positions[live], tick)
            steps = [shields[k].step(positions[k], rankings[j]) for j, k in enumerate(live)]
            actions = np.stack([s.actions for s in steps])
            overridden = [s.overridden for s in steps]
            policy.executed(actions)
        for j, k in enumerate(live):
            step_obs, _, _, info = envs[k].step(actions[j])
            obs[k] = step_obs
            positions[k] = envs[k].positions
            trackers[k].update(positions[k], info["collisions"],
                               None if overridden is None else overridden[j])
        live = shrink(live)
        tick += 1
    if stats is not None and shields is not None:
        stats.extend(s.stats() for s in shields if hasattr(s, "stats"))
    return [t.record() for t in trackers]


def replay_plan(actions: np.ndarray | None, instances: InstanceSet, k: int, max_steps: int, bound: int) -> EpisodeRecord:
    """Execute a (T, N) action plan in the environment (stay once it runs out or is None)."""
    env = _make_env(instances, k, max_steps)
    env.reset()
    tracker = EpisodeTracker(np.asarray(env.positions), instances.goals[k], max_steps, bound)
    stay = np.zeros(instances.starts.shape[1], dtype=np.int64)
    t = 0
    while not tracker.done:
        step_actions = actions[t] if actions is not None and t < len(actions) else stay
        _, _, _, info = env.step(step_actions)
        tracker.update(np.asarray(env.positions), info["collisions"])
        t += 1
    return tracker.record()


def run_planner(planner, instances: InstanceSet, max_steps: int) -> tuple[list[EpisodeRecord], float, int]:
    from mapf_fleet.coordination.planners import positions_to_actions

    bounds = lower_bounds(instances)
    records, plan_time, failures = [], 0.0, 0
    for k in range(len(instances)):
        result = planner.plan(instances.maps[k], instances.starts[k], instances.goals[k])
        plan_time += result.runtime
        failures += not result.complete
        actions = positions_to_actions(result.positions)
        records.append(replay_plan(actions, instances, k, max_steps, bounds[k]))
    return records, plan_time, failures


# --- jobs, in-process or in worker processes --------------------------------------------------

@dataclass(frozen=True)
class Job:
    spec: PolicySpec
    scenario: Scenario
    instances: InstanceSet
    chunk: int  # position of this chunk in the scenario's instance order


_POLICY_CACHE: dict[PolicySpec, object] = {}


def init_worker() -> None:
    """A rollout process's settings: one torch thread, ROS discovery on this machine."""
    # Evaluation never imports rclpy, but a worker must not reach other machines if something does.
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass


def process_pool(workers: int) -> ProcessPoolExecutor:
    """`workers` rollout processes, each set up by `init_worker`. Spawned, not forked: a fork
    would copy the parent's torch threads and the locks they hold."""
    import multiprocessing

    return ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=init_worker)


def cached_policy(spec: PolicySpec):
    """`build_policy(spec)`, built once a process (a worker runs many chunks of one policy)."""
    policy = _POLICY_CACHE.get(spec)
    if policy is None:
        policy = _POLICY_CACHE[spec] = build_policy(spec)
    return policy


def run_job(job: Job) -> tuple[list[EpisodeRecord], float, float | None, int]:
    policy = cached_policy(job.spec)
    began = time.perf_counter()
    if job.spec.is_planner:
        records, plan_time, failures = run_planner(policy, job.instances, job.scenario.max_steps)
    else:
        records, plan_time, failures = run_decentralized(
            policy, job.instances, job.scenario.max_steps, job.spec.conflict_rule,
            planning_budget=job.spec.planning_budget, guidance=job.spec.guidance), None, 0
    return records, time.perf_counter() - began, plan_time, failures


def make_jobs(specs: list[PolicySpec], scenarios: list[tuple[Scenario, InstanceSet]], batch_size: int, workers: int) -> list[Job]:
    """Split each (policy, scenario) into chunks of at most `batch_size` episodes, and into at
    least `workers` chunks so that every process has work."""
    if batch_size < 1:
        raise ValueError(f"--batch-size must be positive, got {batch_size}")
    jobs = []
    for spec in specs:
        for scenario, instances in scenarios:
            chunks = max(math.ceil(len(instances) / batch_size), min(workers, len(instances)))
            for c, index in enumerate(np.array_split(np.arange(len(instances)), chunks)):
                jobs.append(Job(spec, scenario, instances.subset(index), c))
    return jobs


def evaluate(
    specs: list[PolicySpec],
    scenarios: list[tuple[Scenario, InstanceSet]],
    *,
    workers: int = 1,
    batch_size: int = 200,
    progress=None,
) -> list[ScenarioResult]:
    """Every policy on every scenario; `progress(done, total, job)` is called after each job."""
    if workers < 1:
        raise ValueError(f"--workers must be positive, got {workers}")
    jobs = make_jobs(specs, scenarios, batch_size, workers)
    outputs: dict[int, tuple] = {}
    if workers == 1:
        init_worker()
        for i, job in enumerate(jobs):
            outputs[i] = run_job(job)
            if progress:
                progress(len(outputs), len(jobs), job)
    else:
        # Large agent counts first, so the longest jobs do not end up last on one core.
        order = sorted(range(len(jobs)), key=lambda i: -jobs[i].scenario.num_agents * jobs[i].scenario.max_steps)
        with process_pool(workers) as pool:
            futures = {pool.submit(run_job, jobs[i]): i for i in order}
            from concurrent.futures import as_completed

            for future in as_completed(futures):
                i = futures[future]
                outputs[i] = future.result()
                if progress:
                    progress(len(outputs), len(jobs), jobs[i])

    results = []
    for spec in specs:
        for scenario, instances in scenarios:
            mine = sorted((jobs[i].chunk, outputs[i]) for i in range(len(jobs))
                          if jobs[i].spec == spec and jobs[i].scenario == scenario)
            records = [r for _, out in mine for r in out[0]]
            plan_times = [out[2] for _, out in mine if out[2] is not None]
            results.append(
                ScenarioResult(
                    policy=spec.name,
                    scenario=scenario,
                    source=instances.source,
                    episodes=records,
                    compute_time=sum(out[1] for _, out in mine),
                    plan_time=sum(plan_times) if plan_times else None,
                    plan_failures=sum(out[3] for _, out in mine),
                )
            )
    return results
