"""Where a fleet's instance comes from (no rclpy): an instance YAML file, a map file (MovingAI
.map, with a .scen for starts and goals, or a building's Nav2 map_server YAML + image, see
`grid.nav2_map`) with starts and goals drawn from the seed when no .scen is given, or a
generated random instance.

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
    cell_size: float = 0.0  # Nav2 maps: metres per cell (0: one image pixel per cell)

    def __post_init__(self):
        if self.num_robots < 1:
            raise ValueError(f"num_robots must be >= 1, got {self.num_robots}")
        if self.size < 2:
            raise ValueError(f"size must be >= 2, got {self.size}")
        if not 0.0 <= self.density < 1.0:
            raise ValueError(f"density must be in [0, 1), got {self.density}")
        if self.scen_file and not self.map_file:
            raise ValueError(f"scen_file {self.scen_file!r} needs its map_file")
        if self.scen_file and self.is_nav2:
            raise ValueError(f"scen_file {self.scen_file!r} goes with a MovingAI .map, not the "
                             f"Nav2 map {self.map_file!r}")
        if self.cell_size < 0:
            raise ValueError(f"cell_size must be >= 0 (0: the map image's resolution), got "
                             f"{self.cell_size}")

    @property
    def is_nav2(self) -> bool:
        return Path(self.map_file).suffix.lower() in (".yaml", ".yml")

    def geometry(self) -> tuple[float, float, float] | None:
        """(resolution, origin_x, origin_y) of a Nav2 map (the map frame's metres), else None
        (the node's `resolution` / origin parameters place the grid)."""
        if not self.map_file or not self.is_nav2:
            return None
        return self._nav2().geometry

    def _nav2(self):
        from mapf_fleet.grid.nav2_map import read_nav2_map

        found = getattr(self, "_nav2_map", None)
        if found is None:
            found = read_nav2_map(self.map_file, self.cell_size or None)
            object.__setattr__(self, "_nav2_map", found)  # frozen: cache the parsed map
        return found

    def grid(self) -> np.ndarray:
        from mapf_fleet.grid.movingai import read_map

        return np.asarray(self._nav2().grid if self.is_nav2 else read_map(self.map_file))

    def load(self):
        from mapf_fleet.grid.instance import generate_instance

        if self.instance_file:
            return load_instance_yaml(self.instance_file)
        if self.scen_file:
            from mapf_fleet.grid.movingai import load_movingai_instances

            return load_movingai_instances(self.map_file, self.scen_file, self.num_robots).validate()
        if self.map_file:  # a map without a .scen: starts and goals drawn from the seed
            from mapf_fleet.grid.maps import place_agents

            return place_agents(self.grid(), self.num_robots, np.random.default_rng(self.seed))
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
