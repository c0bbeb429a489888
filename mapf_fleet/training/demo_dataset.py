"""Demonstration dataset from the classical planners, in resumable shards (issue 18 item 2).

    mapf-fleet demos --out cache/demos/mix1 --kinds random maze rooms warehouse \\
        --sizes 40 --agents 16 32 64 --count 100 --time-limit 5

Instances: for every (kind, size, agents) combination of the spec, `count` instances of
`mapf_fleet.grid.maps.generate_kind_instance`, instance i with the seed
`instance_seed(seed, kind, size, agents, i)` (recorded, so one manifest entry regenerates its
instance). Planner: LaCAM (`mapf_fleet.coordination.planners.ClassicalPlanner`, pymapf) with the
time limit per connected region; when LaCAM leaves agents without a plan (time limit reached, or
a region it proves unsolvable), PIBT with the same limit, and the plan that leaves fewer agents
unplanned is kept (LaCAM on a tie). The plan is replayed through `MAPFEnv` (the training
environment and its conflict rules) for at most `max_steps` steps; `solved` means every agent
stood on its goal within them, `steps` is the number of steps played.

Files in the output directory:
  - `<kind>_<size>x<size>_<agents>a_<chunk>.npz`: one shard of up to `shard_size` instances of
    one combination: `grids` (K, S, S) uint8, `starts`, `goals` (K, N, 2) int16, `actions`
    (K, T, N) int8 (DHC action order, padded with 0 = stay beyond `steps`), `steps` (K,) int32,
    `solved` (K,) bool, `seeds` (K,) uint64, and `meta` (a JSON string: the shard's manifest
    entry, so a shard describes itself);
  - `manifest.json`: the spec and, per finished shard, its instances (kind, size, agents, seed,
    planner, time limit, solved, steps, unplanned agents, planning seconds).
Both are written atomically (a temporary file in the same directory, then `os.replace`), the
shard first. A run that is killed loses at most the shards in progress: a rerun with the same
spec skips the shards in the manifest, adopts a finished shard that the manifest missed (killed
between the two writes) from its own `meta`, removes stale temporary files and plans the rest.
A rerun with another spec stops with an error naming the differing field.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import sys
import time
import zlib
from pathlib import Path

import numpy as np

from mapf_fleet.files import TMP_MARK, atomic_write

MANIFEST = "manifest.json"
FORMAT_VERSION = 1


@dataclasses.dataclass(frozen=True)
class DemoSpec:
    kinds: tuple = ("random",)
    sizes: tuple = (40,)
    agents: tuple = (16,)
    count: int = 10  # instances per (kind, size, agents)
    time_limit: float = 5.0  # seconds per planner call (per connected region)
    max_steps: int = 256  # replay limit through MAPFEnv
    seed: int = 0
    shard_size: int = 16  # instances per shard file

    def __post_init__(self):
        from mapf_fleet.grid.maps import MAP_KINDS, capacity

        for name in ("kinds", "sizes", "agents"):
            value = getattr(self, name)
            if isinstance(value, (str, int)) or not value:
                raise ValueError(f"demo spec {name} = {value!r}: must be a non-empty list")
            object.__setattr__(self, name, tuple(value))
        for kind in self.kinds:
            if kind not in MAP_KINDS:
                raise ValueError(f"demo spec kinds: unknown kind {kind!r} (known: {MAP_KINDS})")
        for name, low in (("sizes", 8), ("agents", 1)):
            for value in getattr(self, name):
                if isinstance(value, bool) or int(value) != value or value < low:
                    raise ValueError(f"demo spec {name}: entry {value!r} must be an integer >= {low}")
        object.__setattr__(self, "sizes", tuple(int(v) for v in self.sizes))
        object.__setattr__(self, "agents", tuple(int(v) for v in self.agents))
        for name in ("count", "max_steps", "shard_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < 1:
                raise ValueError(f"demo spec {name} = {value!r}: must be an integer >= 1")
        if isinstance(self.seed, bool) or int(self.seed) != self.seed or self.seed < 0:
            raise ValueError(f"demo spec seed = {self.seed!r}: must be an integer >= 0")
        if not float(self.time_limit) > 0:
            raise ValueError(f"demo spec time_limit = {self.time_limit!r}: must be > 0 seconds")
        for kind in self.kinds:
            for size in self.sizes:
                room = capacity(kind, size)
                if max(self.agents) > room:
                    raise ValueError(f"demo spec agents: {max(self.agents)} agents do not fit "
                                     f"every {kind} map of size {size} (at most {room})")

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v
                for k, v in dataclasses.asdict(self).items()}


@dataclasses.dataclass(frozen=True)
class ShardJob:
    name: str
    kind: str
    size: int
    agents: int
    indices: tuple  # instance numbers i within the combination


def instance_seed(seed: int, kind: str, size: int, agents: int, index: int) -> int:
    """The seed of instance `index` of one combination: independent of the other combinations
    and of the order in which shards are planned."""
    kind_id = zlib.crc32(kind.encode())
    return int(np.random.SeedSequence([seed, kind_id, size, agents, index]).generate_state(
        2, np.uint64)[0] >> np.uint64(1))


def shard_jobs(spec: DemoSpec) -> list[ShardJob]:
    jobs = []
    for kind in spec.kinds:
        for size in spec.sizes:
            for agents in spec.agents:
                for chunk, first in enumerate(range(0, spec.count, spec.shard_size)):
                    last = min(spec.count, first + spec.shard_size)
                    jobs.append(ShardJob(f"{kind}_{size}x{size}_{agents}a_{chunk:05d}", kind,
                                         size, agents, tuple(range(first, last))))
    return jobs


# -- planning ----------------------------------------------------------------------------------
def plan_instance(instance, time_limit: float, max_steps: int, seed: int = 0) -> dict:
    """LaCAM, then PIBT when LaCAM leaves agents unplanned; the plan replayed through MAPFEnv.
    Returns {"planner", "actions" (T, N) int64, "steps", "solved", "unplanned_agents",
    "plan_seconds", "collisions"}."""
    from mapf_fleet.coordination.planners import ClassicalPlanner, positions_to_actions
    from mapf_fleet.grid.env import EnvConfig, MAPFEnv

    began = time.perf_counter()
    result = ClassicalPlanner("lacam", time_limit, seed).plan(instance.grid, instance.starts,
                                                               instance.goals)
    planner = "lacam"
    if not result.complete:
        fallback = ClassicalPlanner("pibt", time_limit, seed).plan(instance.grid, instance.starts,
                                                                   instance.goals)
        if fallback.unsolved_agents < result.unsolved_agents:
            result, planner = fallback, "pibt"
    plan_seconds = time.perf_counter() - began
    plan = positions_to_actions(result.positions)  # (T, N); T = 0 when nothing moves
    env = MAPFEnv(instance, EnvConfig(max_steps=max_steps))
    env.reset()
    played, collisions, success = [], 0, False
    if (instance.starts == instance.goals).all():
        success = True
    done = success
    while not done:
        t = env.steps
        action = plan[t] if t < len(plan) else np.zeros(instance.num_agents, np.int64)
        _, _, done, info = env.step(action)
        played.append(action)
        collisions += int(info["collisions"].sum())
        success = bool(info["success"])
    actions = (np.stack(played) if played
               else np.zeros((0, instance.num_agents), np.int64)).astype(np.int64)
    return {"planner": planner, "actions": actions, "steps": int(len(played)),
            "solved": success, "unplanned_agents": int(result.unsolved_agents),
            "plan_seconds": round(plan_seconds, 4), "collisions": collisions}


def plan_shard(spec: DemoSpec, job: ShardJob) -> tuple[dict, dict]:
    """Generate and plan one shard's instances; return (arrays for the .npz, manifest entry)."""
    from mapf_fleet.grid.maps import generate_kind_instance

    grids, starts, goals, seeds, results, entries = [], [], [], [], [], []
    for index in job.indices:
        seed = instance_seed(spec.seed, job.kind, job.size, job.agents, index)
        instance = generate_kind_instance(job.kind, job.size, job.agents, seed)
        result = plan_instance(instance, spec.time_limit, spec.max_steps)
        grids.append(instance.grid)
        starts.append(instance.starts)
        goals.append(instance.goals)
        seeds.append(seed)
        results.append(result)
        entries.append({"index": index, "kind": job.kind, "size": job.size,
                        "agents": job.agents, "seed": seed, "planner": result["planner"],
                        "time_limit": spec.time_limit, "max_steps": spec.max_steps,
                        "solved": result["solved"], "steps": result["steps"],
                        "unplanned_agents": result["unplanned_agents"],
                        "collisions": result["collisions"],
                        "plan_seconds": result["plan_seconds"]})
    horizon = max([r["steps"] for r in results], default=0)
    actions = np.zeros((len(results), horizon, job.agents), np.int8)
    for k, r in enumerate(results):
        actions[k, :r["steps"]] = r["actions"]
    entry = {"file": f"{job.name}.npz", "kind": job.kind, "size": job.size,
             "agents": job.agents, "indices": list(job.indices), "instances": entries}
    arrays = {"grids": np.stack(grids).astype(np.uint8),
              "starts": np.stack(starts).astype(np.int16),
              "goals": np.stack(goals).astype(np.int16), "actions": actions,
              "steps": np.array([r["steps"] for r in results], np.int32),
              "solved": np.array([r["solved"] for r in results], bool),
              "seeds": np.array(seeds, np.uint64),
              "meta": np.array(json.dumps(entry))}
    return arrays, entry


# -- files -------------------------------------------------------------------------------------
def _atomic_write(path: Path, data: bytes) -> None:
    atomic_write(path, data)  # the project's one writer: temporary file, fsync, os.replace


def write_shard(path: Path, arrays: dict) -> None:
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    _atomic_write(path, buffer.getvalue())


def read_shard(path: str | Path) -> dict:
    """A shard's arrays, with `meta` decoded to its manifest entry (dict)."""
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["meta"] = json.loads(str(arrays["meta"]))
    return arrays


def write_manifest(out: Path, manifest: dict) -> None:
    _atomic_write(out / MANIFEST, (json.dumps(manifest, indent=1) + "\n").encode())


def load_manifest(out: str | Path) -> dict:
    with open(Path(out) / MANIFEST) as handle:
        return json.load(handle)


def _open_manifest(out: Path, spec: DemoSpec) -> dict:
    path = out / MANIFEST
    if not path.exists():
        return {"format": FORMAT_VERSION, "spec": spec.to_dict(), "shards": {}}
    manifest = load_manifest(out)
    saved = manifest.get("spec", {})
    for key, value in spec.to_dict().items():
        if saved.get(key) != value:
            raise ValueError(f"{path}: the dataset was made with {key} = {saved.get(key)!r}, "
                             f"this run asks for {value!r}; use another --out directory")
    return manifest


# -- driver ------------------------------------------------------------------------------------
def generate_dataset(out: str | Path, spec: DemoSpec, workers: int = 1, progress: bool = True,
                     on_shard=None) -> dict:
    """Plan every shard of `spec` not yet in `out`'s manifest; return the manifest.
    `on_shard(name)` is called after each shard is recorded (tests use it to interrupt)."""
    from tqdm import tqdm

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for stale in out.glob(f"*{TMP_MARK}*"):
        stale.unlink()
    manifest = _open_manifest(out, spec)
    jobs = shard_jobs(spec)
    todo = []
    for job in jobs:
        if job.name in manifest["shards"] and (out / f"{job.name}.npz").exists():
            continue
        adopted = _adopt(out, job)
        if adopted is not None:
            manifest["shards"][job.name] = adopted
            continue
        todo.append(job)
    write_manifest(out, manifest)
    done = sum(len(job.indices) for job in jobs) - sum(len(job.indices) for job in todo)
    bar = tqdm(total=sum(len(j.indices) for j in jobs), initial=done, unit="instance",
               desc=f"demos {out.name}", disable=not progress, dynamic_ncols=True)

    def record(job: ShardJob, arrays: dict, entry: dict) -> None:
        write_shard(out / entry["file"], arrays)
        manifest["shards"][job.name] = entry
        write_manifest(out, manifest)
        bar.update(len(job.indices))
        solved = sum(s["solved"] for s in manifest_instances(manifest))
        bar.set_postfix(solved=f"{solved}/{bar.n}")
        if on_shard is not None:
            on_shard(job.name)

    try:
        if workers <= 1:
            for job in todo:
                record(job, *plan_shard(spec, job))
        else:
            from concurrent.futures import ProcessPoolExecutor, as_completed

            with ProcessPoolExecutor(workers) as pool:
                futures = {pool.submit(plan_shard, spec, job): job for job in todo}
                for future in as_completed(futures):
                    record(futures[future], *future.result())
    finally:
        bar.close()
    return manifest


def _adopt(out: Path, job: ShardJob) -> dict | None:
    """The manifest entry of a finished shard file the manifest missed, or None."""
    path = out / f"{job.name}.npz"
    if not path.exists():
        return None
    try:
        entry = read_shard(path)["meta"]
    except Exception:  # a damaged file: plan the shard again
        return None
    if entry.get("indices") != list(job.indices) or entry.get("kind") != job.kind:
        return None
    return entry


def manifest_instances(manifest: dict) -> list[dict]:
    return [inst for shard in manifest["shards"].values() for inst in shard["instances"]]


def summarize(manifest: dict) -> str:
    rows = {}
    for inst in manifest_instances(manifest):
        key = (inst["kind"], inst["size"], inst["agents"])
        row = rows.setdefault(key, {"n": 0, "solved": 0, "pibt": 0, "steps": 0, "seconds": 0.0})
        row["n"] += 1
        row["solved"] += inst["solved"]
        row["pibt"] += inst["planner"] == "pibt"
        row["steps"] += inst["steps"]
        row["seconds"] += inst["plan_seconds"]
    lines = ["kind       size agents instances solved  pibt  mean steps  mean plan s"]
    for (kind, size, agents), r in sorted(rows.items()):
        lines.append(f"{kind:<10} {size:>4} {agents:>6} {r['n']:>9} {r['solved']:>6} "
                     f"{r['pibt']:>5} {r['steps'] / r['n']:>11.1f} {r['seconds'] / r['n']:>12.3f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mapf-fleet demos", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="dataset directory (created; rerun to resume)")
    parser.add_argument("--kinds", nargs="+", default=["random"],
                        help="map kinds: random maze rooms warehouse")
    parser.add_argument("--sizes", nargs="+", type=int, default=[40], help="map sides")
    parser.add_argument("--agents", nargs="+", type=int, default=[16], help="agent counts")
    parser.add_argument("--count", type=int, default=10,
                        help="instances per (kind, size, agents) combination")
    parser.add_argument("--time-limit", type=float, default=5.0,
                        help="seconds per planner call (LaCAM, then PIBT) per connected region")
    parser.add_argument("--max-steps", type=int, default=256, help="replay step limit")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--shard-size", type=int, default=16, help="instances per shard file")
    parser.add_argument("--workers", type=int, default=1, help="planning processes")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        spec = DemoSpec(kinds=args.kinds, sizes=args.sizes, agents=args.agents, count=args.count,
                        time_limit=args.time_limit, max_steps=args.max_steps, seed=args.seed,
                        shard_size=args.shard_size)
        manifest = generate_dataset(args.out, spec, workers=args.workers,
                                    progress=not args.no_progress)
    except ValueError as exc:
        print(f"mapf-fleet demos: {exc}", file=sys.stderr)
        return 2
    print(summarize(manifest))
    return 0


if __name__ == "__main__":
    sys.exit(main())
