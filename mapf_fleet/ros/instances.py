"""Where a fleet's instance comes from (no rclpy): an instance YAML file, MovingAI .map/.scen
files, or a generated random instance.

Instance YAML (e.g. config/fleet/instance_*.yaml):

    grid:            # one string per row: '.' free, '@' or '#' or 'T' obstacle
      - "....@..."
    starts: [[0, 0], [1, 2]]   # (row, col) per robot
    goals:  [[5, 5], [3, 1]]
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

OBSTACLE_CHARS = set("@#TOW")
FREE_CHARS = set(".G")


@dataclass(frozen=True)
class InstanceSource:
    """Validated description of where the simulator's instance comes from."""

    instance_file: str = ""
    map_file: str = ""
    scen_file: str = ""
    num_robots: int = 8
    size: int = 16
    density: float = 0.3
    seed: int = 0

    def __post_init__(self):
        if self.num_robots < 1:
            raise ValueError(f"num_robots must be >= 1, got {self.num_robots}")
        if self.size < 2:
            raise ValueError(f"size must be >= 2, got {self.size}")
        if not 0.0 <= self.density < 1.0:
            raise ValueError(f"density must be in [0, 1), got {self.density}")
        if bool(self.map_file) != bool(self.scen_file):
            raise ValueError("map_file and scen_file go together: give both or neither "
                             f"(map_file={self.map_file!r}, scen_file={self.scen_file!r})")

    def load(self):
        from mapf_fleet.grid.instance import generate_instance

        if self.instance_file:
            return load_instance_yaml(self.instance_file)
        if self.map_file:
            from mapf_fleet.grid.movingai import load_movingai_instances

            return load_movingai_instances(self.map_file, self.scen_file, self.num_robots).validate()
        return generate_instance(self.size, self.num_robots, self.density, self.seed)


def load_instance_yaml(path):
    from mapf_fleet.grid.instance import Instance

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"instance file not found: {path}") from None
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not valid YAML ({exc})") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping with grid, starts, goals")
    for key in ("grid", "starts", "goals"):
        if key not in data:
            raise ValueError(f"{path}: missing field {key!r}")
    rows = data["grid"]
    if not isinstance(rows, list) or not rows or not all(isinstance(r, str) for r in rows):
        raise ValueError(f"{path}: field 'grid' must be a list of row strings")
    width = len(rows[0])
    grid = np.zeros((len(rows), width), dtype=np.uint8)
    for r, row in enumerate(rows):
        if len(row) != width:
            raise ValueError(f"{path}: grid row {r} has length {len(row)}, expected {width}")
        for c, char in enumerate(row):
            if char in OBSTACLE_CHARS:
                grid[r, c] = 1
            elif char not in FREE_CHARS:
                raise ValueError(f"{path}: grid row {r} col {c}: unknown cell {char!r}")
    try:
        instance = Instance(grid, np.asarray(data["starts"]), np.asarray(data["goals"]))
        return instance.validate()
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc


def dump_instance_yaml(instance, path) -> None:
    rows = ["".join("@" if v else "." for v in row) for row in np.asarray(instance.grid)]
    data = {"grid": rows, "starts": np.asarray(instance.starts).tolist(),
            "goals": np.asarray(instance.goals).tolist()}
    Path(path).write_text(yaml.safe_dump(data, default_flow_style=None, sort_keys=False))
