"""MovingAI benchmark files: .map grids and .scen scenarios (the standard MAPF benchmark format).

.map:  "type octile", "height H", "width W", "map", then H lines of W characters.
       Passable: '.', 'G', 'S'; obstacles: '@', 'O', 'T', 'W'.
.scen: "version 1", then one tab-separated line per agent:
       bucket  map  map_width  map_height  start_x  start_y  goal_x  goal_y  optimal_length
       where x is the column and y the row.
"""

from __future__ import annotations

import dataclasses
from os import PathLike
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from .errors import InstanceError, MapFormatError
from .heuristic import bfs_distances_many
from .instance import Instance

PASSABLE = frozenset(".GS")
OBSTACLE = frozenset("@OTW")


@dataclasses.dataclass(frozen=True)
class ScenarioEntry:
    """One .scen line; start and goal in (row, col)."""

    bucket: int
    map_name: str
    map_width: int
    map_height: int
    start: tuple[int, int]
    goal: tuple[int, int]
    optimal_length: float
    line: int | None = dataclasses.field(default=None, compare=False)  # in the file read


def _lines(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="ascii").splitlines()
    except UnicodeDecodeError as exc:
        line = path.read_bytes()[:exc.start].count(b"\n") + 1
        raise MapFormatError(path, line, "non-ASCII byte in file") from exc


def _header_value(path: Path, lines: list[str], number: int, key: str) -> str:
    if number > len(lines):
        raise MapFormatError(path, number, f"file ends before the '{key}' header line")
    parts = lines[number - 1].split()
    if len(parts) < 1 or parts[0].lower() != key:
        raise MapFormatError(path, number, f"expected '{key} ...', got {lines[number - 1]!r}")
    if key == "map":
        return ""
    if len(parts) != 2:
        raise MapFormatError(path, number, f"expected '{key} <value>', got {lines[number - 1]!r}")
    return parts[1]


def _positive_int(path: Path, number: int, key: str, text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise MapFormatError(path, number, f"{key} {text!r} is not an integer") from None
    if value < 1:
        raise MapFormatError(path, number, f"{key} must be >= 1, got {value}")
    return value


def read_map(path: str | PathLike) -> np.ndarray:
    """uint8 (H, W) grid, 1 = obstacle, from a MovingAI .map file."""
    path = Path(path)
    lines = _lines(path)
    _header_value(path, lines, 1, "type")
    height = _positive_int(path, 2, "height", _header_value(path, lines, 2, "height"))
    width = _positive_int(path, 3, "width", _header_value(path, lines, 3, "width"))
    _header_value(path, lines, 4, "map")
    rows = lines[4:]
    while rows and not rows[-1].strip():
        rows.pop()  # tolerate trailing blank lines
    if len(rows) != height:
        raise MapFormatError(path, 5 + min(len(rows), height),
                             f"expected {height} map rows, found {len(rows)}")
    grid = np.zeros((height, width), dtype=np.uint8)
    for r, row in enumerate(rows):
        number = 5 + r
        row = row.rstrip("\r")
        if len(row) != width:
            raise MapFormatError(path, number, f"row has {len(row)} characters, expected {width}")
        for c, char in enumerate(row):
            if char in OBSTACLE:
                grid[r, c] = 1
            elif char not in PASSABLE:
                raise MapFormatError(path, number, f"unknown map character {char!r} at column {c}")
    return grid


def write_map(path: str | PathLike, grid) -> None:
    """Write a grid (1 = obstacle) as a MovingAI .map file ('.' free, '@' obstacle)."""
    grid = np.asarray(grid)
    if grid.ndim != 2:
        raise ValueError(f"grid must be 2-D, got shape {grid.shape}")
    h, w = grid.shape
    rows = ["".join("@" if v else "." for v in row) for row in (grid != 0)]
    text = "\n".join(["type octile", f"height {h}", f"width {w}", "map", *rows]) + "\n"
    Path(path).write_text(text, encoding="ascii")


def read_scen(path: str | PathLike) -> list[ScenarioEntry]:
    """Entries of a MovingAI .scen file (version 1), in file order."""
    path = Path(path)
    lines = _lines(path)
    if not lines or lines[0].split()[:1] != ["version"]:
        raise MapFormatError(path, 1, "expected a 'version 1' header line")
    version = lines[0].split()[1:2]
    if version not in (["1"], ["1.0"]):
        raise MapFormatError(path, 1, f"unsupported scenario version {lines[0]!r}")
    entries = []
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        fields = line.split("\t") if "\t" in line else line.split()
        fields = [f.strip() for f in fields]
        if len(fields) != 9:
            raise MapFormatError(path, number, f"expected 9 fields, found {len(fields)}")
        try:
            bucket, width, height, sx, sy, gx, gy = (int(fields[i]) for i in (0, 2, 3, 4, 5, 6, 7))
            optimal = float(fields[8])
        except ValueError:
            raise MapFormatError(path, number, f"non-numeric field in {line!r}") from None
        for name, x, y in (("start", sx, sy), ("goal", gx, gy)):
            if not (0 <= x < width and 0 <= y < height):
                raise MapFormatError(path, number, f"{name} (x={x}, y={y}) is outside the "
                                                   f"{width}x{height} map")
        entries.append(ScenarioEntry(bucket, fields[1], width, height, (sy, sx), (gy, gx), optimal,
                                     line=number))
    return entries


def write_scen(path: str | PathLike, entries: Iterable[ScenarioEntry]) -> None:
    """Write scenario entries as a MovingAI .scen file (version 1)."""
    out = ["version 1"]
    for e in entries:
        out.append("\t".join(str(v) for v in (
            e.bucket, e.map_name, e.map_width, e.map_height, e.start[1], e.start[0], e.goal[1],
            e.goal[0], f"{float(e.optimal_length):.8g}")))
    Path(path).write_text("\n".join(out) + "\n", encoding="ascii")


def instance_to_scenario(instance: Instance, map_name: str, bucket: int = 0
                         ) -> list[ScenarioEntry]:
    """Scenario entries for an instance; optimal_length is the 4-connected BFS distance."""
    h, w = instance.size
    dist = bfs_distances_many(instance.grid, instance.goals)
    n = instance.num_agents
    lengths = dist[np.arange(n), instance.starts[:, 0], instance.starts[:, 1]]
    return [ScenarioEntry(bucket, map_name, w, h, tuple(map(int, s)), tuple(map(int, g)), float(d))
            for s, g, d in zip(instance.starts, instance.goals, lengths)]


def map_file_name(map_name: str) -> str:
    """The file name a .scen line's map column names ("maps/den312d.map" -> "den312d.map")."""
    return map_name.replace("\\", "/").rsplit("/", 1)[-1]


def check_scen_map(map_path: str | PathLike, scen_path: str | PathLike,
                   entries: Sequence[ScenarioEntry]) -> None:
    """MapFormatError naming both files when a .scen line's map column (column 2) names another
    map file than `map_path`: a .scen of another map is refused before its cells are checked."""
    map_path = Path(map_path)
    for k, e in enumerate(entries):
        named = map_file_name(e.map_name)
        if named and named != map_path.name:
            raise MapFormatError(scen_path, e.line, f"entry {k} is for map {e.map_name!r} (column 2), "
                                                    f"not {map_path}: give each map its own .scen")


def load_movingai_instances(map_path: str | PathLike, scen_path: str | PathLike,
                            num_agents: int) -> Instance:
    """The instance made of the map and the first `num_agents` scenario entries (validated).
    Errors name the .scen file and line: an entry of another map (column 2), a start or goal on
    an obstacle, an unreachable goal."""
    grid = read_map(map_path)
    entries: Sequence[ScenarioEntry] = read_scen(scen_path)
    if num_agents < 1 or num_agents > len(entries):
        raise MapFormatError(scen_path, None, f"asked for {num_agents} agents, the file has "
                                              f"{len(entries)} entries")
    check_scen_map(map_path, scen_path, entries[:num_agents])
    h, w = grid.shape
    for k, e in enumerate(entries[:num_agents]):
        if (e.map_height, e.map_width) != (h, w):
            raise MapFormatError(scen_path, e.line, f"entry {k} is for a {e.map_width}x"
                                                    f"{e.map_height} map, {map_path} is {w}x{h}")
    starts = np.array([e.start for e in entries[:num_agents]], dtype=np.int64)
    goals = np.array([e.goal for e in entries[:num_agents]], dtype=np.int64)
    try:
        return Instance(grid, starts, goals).validate()
    except InstanceError as exc:
        line = entries[exc.agent].line if exc.agent is not None and exc.agent < num_agents else None
        cell = "" if exc.cell is None else f" (x={exc.cell[1]}, y={exc.cell[0]} in .scen terms)"
        raise MapFormatError(scen_path, line, f"{exc}{cell}, on map {map_path}") from exc
