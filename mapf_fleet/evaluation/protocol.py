"""The test protocol: which scenarios (map size x agent count, step limit) and which instances.

`ProtocolConfig` is read from `config/evaluation/paper.yaml`. Instances of a scenario come from
the DHC authors' published test sets when present (40x40), otherwise they are generated once
from a fixed seed and cached on disk (`cache/evaluation/` of a checkout, git-ignored; when
installed, ~/.cache/mapf_fleet/evaluation) in the same .npz layout as the published sets
(`maps` (K,H,W) uint8, `starts`/`goals` (K,N,2) int16, (row, col)).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapf_fleet import paths

# installed: <prefix>/share/mapf_fleet/config/...; from a checkout: config/... (mapf_fleet.paths)
DEFAULT_CONFIG = paths.data_path("config", "evaluation", "paper.yaml")
DEFAULT_TESTSETS = paths.DEFAULT_TESTSETS
DEFAULT_CACHE = paths.cache_dir("evaluation")


class ProtocolError(ValueError):
    """A protocol file or option is invalid; the message names the file/field and value."""


@dataclass(frozen=True)
class MapProtocol:
    size: int
    agents: tuple[int, ...]
    max_steps: int
    testset: str | None = None  # file-name pattern with {agents}, or None = always generate

    def __post_init__(self):
        if not isinstance(self.size, int) or self.size < 2:
            raise ProtocolError(f"maps[].size must be an integer >= 2, got {self.size!r}")
        if not self.agents or any(not isinstance(n, int) or n < 1 for n in self.agents):
            raise ProtocolError(f"maps[size={self.size}].agents must be positive integers, got {self.agents!r}")
        if not isinstance(self.max_steps, int) or self.max_steps < 1:
            raise ProtocolError(f"maps[size={self.size}].max_steps must be a positive integer, got {self.max_steps!r}")
        if self.testset is not None and "{agents}" not in self.testset:
            raise ProtocolError(f"maps[size={self.size}].testset must contain '{{agents}}', got {self.testset!r}")


@dataclass(frozen=True)
class ProtocolConfig:
    maps: tuple[MapProtocol, ...]
    density: float = 0.3
    instances: int = 200
    seed: int = 0
    references: tuple[str, ...] = ("heuristic", "lacam")
    planner_time_limit: float = 10.0
    planner_seed: int = 0

    def __post_init__(self):
        if not 0.0 <= self.density < 1.0:
            raise ProtocolError(f"density must be in [0, 1), got {self.density!r}")
        if not isinstance(self.instances, int) or self.instances < 1:
            raise ProtocolError(f"instances must be a positive integer, got {self.instances!r}")
        if not self.maps:
            raise ProtocolError("maps must list at least one map size")
        if self.planner_time_limit <= 0:
            raise ProtocolError(f"planner.time_limit must be positive, got {self.planner_time_limit!r}")

    @classmethod
    def from_yaml(cls, path: str | Path = DEFAULT_CONFIG) -> "ProtocolConfig":
        import yaml

        path = Path(path)
        try:
            raw = yaml.safe_load(path.read_text())
        except OSError as exc:
            raise ProtocolError(f"{path}: cannot read protocol file ({exc})") from exc
        if not isinstance(raw, dict):
            raise ProtocolError(f"{path}: expected a mapping at the top level")
        known = {"maps", "density", "instances", "seed", "references", "planner"}
        unknown = set(raw) - known
        if unknown:
            raise ProtocolError(f"{path}: unknown field(s) {sorted(unknown)}; known: {sorted(known)}")
        try:
            maps = tuple(
                MapProtocol(
                    size=m["size"], agents=tuple(m["agents"]), max_steps=m["max_steps"], testset=m.get("testset")
                )
                for m in raw.get("maps", [])
            )
            planner = raw.get("planner") or {}
            return cls(
                maps=maps,
                density=float(raw.get("density", 0.3)),
                instances=raw.get("instances", 200),
                seed=int(raw.get("seed", 0)),
                references=tuple(raw.get("references", ("heuristic", "lacam"))),
                planner_time_limit=float(planner.get("time_limit", 10.0)),
                planner_seed=int(planner.get("seed", 0)),
            )
        except ProtocolError as exc:
            raise ProtocolError(f"{path}: {exc}") from exc
        except (KeyError, TypeError) as exc:
            raise ProtocolError(f"{path}: malformed maps entry ({exc!r})") from exc


@dataclass(frozen=True)
class Scenario:
    """One column of the tables: a map family, an agent count and a step limit."""

    map_name: str  # "40x40", "80x80", or a MovingAI map's file stem
    num_agents: int
    max_steps: int
    size: int | None = None  # square protocol maps only
    testset: str | None = field(default=None, compare=False)

    @property
    def key(self) -> str:
        return f"{self.map_name}/{self.num_agents}"


def protocol_scenarios(
    config: ProtocolConfig, sizes: list[int] | None = None, agents: list[int] | None = None
) -> list[Scenario]:
    """The scenarios of `config`, optionally restricted to some map sizes and agent counts."""
    known_sizes = [m.size for m in config.maps]
    for s in sizes or []:
        if s not in known_sizes:
            raise ProtocolError(f"--sizes: {s} is not a map size of the protocol {known_sizes}")
    scenarios = []
    for m in config.maps:
        if sizes and m.size not in sizes:
            continue
        for n in m.agents:
            if agents and n not in agents:
                continue
            scenarios.append(Scenario(f"{m.size}x{m.size}", n, m.max_steps, m.size, m.testset))
    if not scenarios:
        raise ProtocolError(f"no scenario left after selecting sizes={sizes} agents={agents}")
    return scenarios


@dataclass(frozen=True)
class InstanceSet:
    """Instances of one scenario as stacked arrays (cheap to pickle to worker processes)."""

    maps: np.ndarray  # (K, H, W) uint8
    starts: np.ndarray  # (K, N, 2)
    goals: np.ndarray  # (K, N, 2)
    source: str  # where they came from, for the report

    def __len__(self) -> int:
        return len(self.maps)

    def subset(self, index) -> "InstanceSet":
        return InstanceSet(self.maps[index], self.starts[index], self.goals[index], self.source)

    def instance(self, k: int):
        from mapf_fleet.grid.instance import Instance

        return Instance(self.maps[k].astype(np.uint8), self.starts[k].astype(np.int64), self.goals[k].astype(np.int64))

    @classmethod
    def from_instances(cls, instances, source: str) -> "InstanceSet":
        return cls(
            np.stack([np.asarray(i.grid, dtype=np.uint8) for i in instances]),
            np.stack([np.asarray(i.starts, dtype=np.int64) for i in instances]),
            np.stack([np.asarray(i.goals, dtype=np.int64) for i in instances]),
            source,
        )


def _read_npz(path: Path) -> InstanceSet:
    with np.load(path) as data:
        missing = {"maps", "starts", "goals"} - set(data.files)
        if missing:
            raise ProtocolError(f"{path}: missing array(s) {sorted(missing)}")
        return InstanceSet(data["maps"].astype(np.uint8), data["starts"].astype(np.int64), data["goals"].astype(np.int64), str(path))


def _write_npz_atomic(path: Path, maps, starts, goals) -> None:
    from mapf_fleet.files import atomic_write

    atomic_write(path, lambda f: np.savez_compressed(
        f, maps=maps.astype(np.uint8), starts=starts.astype(np.int16), goals=goals.astype(np.int16)))


def generator_tag() -> str:
    """Short hash of the instance generator's source: a cache made by another version of
    `mapf_fleet.grid.instance` is not reused."""
    import hashlib
    import inspect

    from mapf_fleet.grid import instance

    return hashlib.sha1(inspect.getsource(instance).encode()).hexdigest()[:8]


def generated_instances(size: int, num_agents: int, count: int, density: float, seed: int) -> InstanceSet:
    """`count` instances; instance i is drawn from the seed sequence (seed, size, num_agents, i),
    so any prefix is the same whatever `count` is."""
    from mapf_fleet.grid.instance import generate_instance

    made = [
        generate_instance(size, num_agents, density, np.random.default_rng([seed, size, num_agents, i]))
        for i in range(count)
    ]
    return InstanceSet.from_instances(made, f"generated (seed {seed}, density {density})")


def scenario_instances(
    scenario: Scenario,
    count: int,
    *,
    density: float = 0.3,
    seed: int = 0,
    testsets_dir: str | Path | None = DEFAULT_TESTSETS,
    cache_dir: str | Path | None = DEFAULT_CACHE,
) -> InstanceSet:
    """The first `count` instances of a protocol scenario: the published test set when the
    scenario names one and it exists in `testsets_dir`, else generated and cached in `cache_dir`
    (None = no cache)."""
    if scenario.size is None:
        raise ProtocolError(f"scenario {scenario.key} is not a generated protocol scenario")
    if scenario.testset and testsets_dir is not None:
        path = Path(testsets_dir) / scenario.testset.format(agents=scenario.num_agents)
        if path.is_file():
            from mapf_fleet.grid.instance import load_dhc_testset

            published = InstanceSet.from_instances(load_dhc_testset(path), str(path))
            if published.maps.shape[1:] != (scenario.size, scenario.size) or published.starts.shape[1] != scenario.num_agents:
                raise ProtocolError(
                    f"{path}: expected {scenario.size}x{scenario.size} maps with {scenario.num_agents} agents, "
                    f"got maps {published.maps.shape} starts {published.starts.shape}"
                )
            if count > len(published):
                raise ProtocolError(f"--instances {count}: {path} holds only {len(published)} instances")
            subset = published.subset(slice(0, count))
            return InstanceSet(subset.maps, subset.starts, subset.goals, f"published DHC test sets ({scenario.testset})")

    source = f"generated (seed {seed}, density {density})"
    if scenario.testset and testsets_dir is not None:
        # say it where the table says where its instances came from: generated 40x40 sets are
        # not the paper's and their figures are not comparable with the published ones
        missing = Path(testsets_dir) / scenario.testset.format(agents=scenario.num_agents)
        absent = f"; the published set {missing} is absent"
    else:
        absent = ""
    if cache_dir is None:
        made = generated_instances(scenario.size, scenario.num_agents, count, density, seed)
        return InstanceSet(made.maps, made.starts, made.goals, source + absent)
    cache = Path(cache_dir) / (
        f"{scenario.size}x{scenario.size}_{scenario.num_agents}agents_d{density:g}_seed{seed}_{generator_tag()}.npz"
    )
    if cache.is_file():
        cached = _read_npz(cache)
        if len(cached) >= count:
            subset = cached.subset(slice(0, count))
            return InstanceSet(subset.maps, subset.starts, subset.goals, source + ", cached" + absent)
    made = generated_instances(scenario.size, scenario.num_agents, count, density, seed)
    _write_npz_atomic(cache, made.maps, made.starts, made.goals)
    return InstanceSet(made.maps, made.starts, made.goals, source + absent)


def _expand(items: list[str | Path], suffix: str, flag: str) -> list[Path]:
    """Files of `items`; a folder stands for its *`suffix` files (sorted)."""
    out: list[Path] = []
    for item in items:
        path = Path(item)
        if path.is_dir():
            found = sorted(p for p in path.glob(f"*{suffix}") if p.is_file())
            if not found:
                raise ProtocolError(f"{flag}: no {suffix} file in folder {path}")
            out += found
        elif path.is_file():
            out.append(path)
        else:
            raise ProtocolError(f"{flag}: no such file or folder: {path}")
    return out


def movingai_pairs(maps: list[str | Path], scens: list[str | Path]) -> list[tuple[Path, list[Path]]]:
    """Which .scen files go with which .map file, as [(map, [scen, ...])] in --map order.
    Folders stand for their *.map / *.scen files. One map takes every .scen. Several maps and as
    many .scen files, none given as a folder, pair in order (`--map a.map b.map --scen a.scen
    b.scen`). Otherwise each .scen goes to the map its lines name (column 2 of a MovingAI .scen).
    A .scen of another map is refused when it is loaded (naming both files)."""
    from mapf_fleet.grid.movingai import map_file_name, read_scen

    map_files = _expand(list(maps), ".map", "--map")
    scen_files = _expand(list(scens), ".scen", "--scen")
    if not scen_files:
        raise ProtocolError("--map needs at least one --scen file")
    stems: dict[str, Path] = {}
    for m in map_files:
        if m.stem in stems:
            raise ProtocolError(f"--map: {stems[m.stem]} and {m} have the same name {m.stem!r}")
        stems[m.stem] = m
    if len(map_files) == 1:
        return [(map_files[0], scen_files)]
    folders = any(Path(p).is_dir() for p in [*maps, *scens])
    if not folders and len(scen_files) == len(map_files):
        return [(m, [s]) for m, s in zip(map_files, scen_files)]
    by_name = {m.name: m for m in map_files}
    groups: dict[Path, list[Path]] = {m: [] for m in map_files}
    for scen in scen_files:
        entries = read_scen(scen)
        named = map_file_name(entries[0].map_name) if entries else ""
        if named not in by_name:
            raise ProtocolError(f"{scen}: its lines name map {named!r} (column 2), not one of the "
                                f"--map files {sorted(by_name)}")
        groups[by_name[named]].append(scen)
    alone = [str(m) for m, group in groups.items() if not group]
    if alone:
        raise ProtocolError(f"--scen: no .scen file names the map(s) {', '.join(alone)}")
    return list(groups.items())


# Structured map families of the training mix (`mapf_fleet.grid.maps`), evaluated beside the
# paper's random maps: where a fleet operates (corridors, rooms, aisles) rather than where the
# paper measured.
FAMILY_KINDS = ("maze", "rooms", "warehouse")
FAMILY_AGENTS = (16, 32, 64)
FAMILY_SIZES = (40,)


def family_scenarios(config: "ProtocolConfig", kinds: list[str], count: int, seed: int,
                     sizes: list[int] | None = None, agents: list[int] | None = None,
                     max_steps: int | None = None) -> list[tuple[Scenario, InstanceSet]]:
    """One scenario per (kind, side, agent count) with its `count` instances; the step limit of
    the protocol map of the same side (256 on 40x40, 386 on 80x80; the nearest for other sides)
    unless `max_steps`."""
    from mapf_fleet.grid.maps import capacity

    unknown = [k for k in kinds if k not in FAMILY_KINDS]
    if unknown:
        raise ProtocolError(f"--kinds: unknown map kind(s) {unknown} (known: {', '.join(FAMILY_KINDS)})")
    limits = {m.size: m.max_steps for m in config.maps}
    scenarios = []
    for kind in dict.fromkeys(kinds):
        for size in sizes or FAMILY_SIZES:
            limit = max_steps or limits[min(limits, key=lambda s: (abs(s - size), s))]
            for n in agents or FAMILY_AGENTS:
                if n > capacity(kind, size):
                    raise ProtocolError(f"--kinds {kind}: {n} agents do not fit every {size}x{size} "
                                        f"{kind} map (at most {capacity(kind, size)})")
                scenarios.append((Scenario(f"{kind} {size}x{size}", n, limit),
                                  family_instances(kind, size, n, count, seed)))
    return scenarios


def family_instances(kind: str, size: int, num_agents: int, count: int, seed: int) -> InstanceSet:
    """`count` instances of a structured family; instance i is drawn from the seed sequence
    (seed, kind, size, num_agents, i), so any prefix is the same whatever `count` is."""
    from mapf_fleet.grid.maps import MAP_KINDS, generate_kind_instance

    code = MAP_KINDS.index(kind)
    made = [generate_kind_instance(kind, size, num_agents,
                                   np.random.default_rng([seed, code, size, num_agents, i]))
            for i in range(count)]
    return InstanceSet.from_instances(made, f"generated {kind} maps (seed {seed})")


def movingai_scenarios(
    map_path: str | Path, scen_paths: list[str | Path], num_agents: int, max_steps: int
) -> tuple[Scenario, InstanceSet]:
    """One scenario from a MovingAI map: each .scen file gives one instance (its first
    `num_agents` entries)."""
    from mapf_fleet.grid.movingai import load_movingai_instances

    if not scen_paths:
        raise ProtocolError("--map needs at least one --scen file")
    if num_agents < 1:
        raise ProtocolError(f"--agents must be positive for MovingAI input, got {num_agents}")
    instances = [load_movingai_instances(map_path, scen, num_agents) for scen in scen_paths]
    scenario = Scenario(Path(map_path).stem, num_agents, max_steps)
    return scenario, InstanceSet.from_instances(instances, f"MovingAI {Path(map_path).name} ({len(scen_paths)} scen)")
