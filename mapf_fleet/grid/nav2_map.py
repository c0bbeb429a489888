"""Nav2 map_server maps (a YAML file and its PGM/PNG image) as grids of the project.

The YAML (Nav2 map_server, nav2_map_server/src/map_io.cpp `loadMapYaml`):
    image: building.pgm        # relative to the YAML file's folder (or absolute)
    resolution: 0.05           # metres per pixel
    origin: [-10.0, -5.0, 0.0] # [x, y, yaw] of the LOWER-LEFT pixel's lower-left corner
    negate: 0                  # 0/1 or false/true
    occupied_thresh: 0.65
    free_thresh: 0.196
    mode: trinary              # optional: trinary (default), scale or raw

Pixel occupancy (map_io.cpp `loadMapFromFile`, reproduced exactly): shade = mean of the R, G, B
channels in [0, 1] (a grey image has R = G = B); in trinary mode an image WITH an alpha channel
averages its alpha in as a fourth channel (map_server does, "to preserve existing behavior": an
opaque black pixel has shade 0.25, not 0); occ = shade if negate else 1 - shade, then
    trinary: occ > occupied_thresh -> 100, occ < free_thresh -> 0, else -1 (unknown)
    scale:   a pixel not fully opaque -> -1; occ > occupied_thresh -> 100; occ < free_thresh -> 0;
             else rint((occ - free) / (occupied - free) * 100)
    raw:     round(shade * 255) when in 0..100, else -1 (negate and thresholds unused)
A pixel BLOCKS when its value is unknown (-1) or >= OCCUPIED_VALUE (50, the same rule as
`mapf_fleet.ros.common.occupancy_to_grid`); in trinary mode that is "occupied or unknown".
Note: Nav2's map_saver writes unknown as grey 205 (occ 0.196) but its default free_thresh is 0.25,
so a map saved with Nav2's defaults reads its unknown space back as FREE in map_server and here
alike (slam_toolbox issue #587); `write_nav2_map` writes ROS 1's free_thresh 0.196 instead.

Rows, cells and metres. map_server puts image row y (row 0 = top of the picture) in
OccupancyGrid row H-1-y, so OccupancyGrid row 0 is the BOTTOM of the picture (lowest y). The grids
here use the OccupancyGrid row order, because `MapGeometry` (mapf_fleet.fleet.topics) and
`grid_to_occupancy` already treat grid row r as OccupancyGrid row r:
    cell (row, col) has its centre at  x = origin_x + (col + 0.5) * cell_size,
                                       y = origin_y + (row + 0.5) * cell_size
so `MapGeometry(*nav2_map.geometry)` places every pose in the right cell and `/fleet/map` carries
the map as map_server would publish it (at cell_size). Printing `grid` top row first therefore
shows the picture upside down; `np.flipud(grid)` is the picture's orientation. (Actions "up" =
row - 1 move towards lower y, as they always have under MapGeometry.)

Downsampling: a cell is k x k pixels, k = cell_size / resolution, a whole number (a cell_size that
is not a whole number of pixels is refused). Cells start at the origin (the lower-left pixel), so a
partial block can only occur at the picture's right and top edges; its missing pixels count as
unknown, i.e. such a cell is blocked. A cell is blocked when ANY of its pixels blocks.

Only yaw = 0 is supported (a rotated map frame would make the cells diagonal in metres); another
yaw is refused with a MapFormatError naming the `origin` field.
"""

from __future__ import annotations

import dataclasses
import math
from os import PathLike
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import yaml

from .errors import MapFormatError
from .movingai import read_map

MODES = ("trinary", "scale", "raw")
OCC_FREE, OCC_OCCUPIED, OCC_UNKNOWN = 0, 100, -1
# OccupancyGrid value from which a pixel is an obstacle (matches ros.common.occupancy_to_grid)
OCCUPIED_VALUE = 50
# map_saver's trinary pixel values (map_io.cpp tryWriteMapToFile)
SAVER_FREE, SAVER_OCCUPIED, SAVER_UNKNOWN = 254, 0, 205
# Thresholds `write_nav2_map` writes: ROS 1 map_saver's, so that grey 205 reads back as unknown
WRITE_OCCUPIED_THRESH, WRITE_FREE_THRESH = 0.65, 0.196
# how far cell_size / resolution may be from a whole number (relative), and yaw from 0 (radians)
_PIXELS_TOLERANCE = 1e-6
_YAW_TOLERANCE = 1e-9
_REQUIRED = ("image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh")


@dataclasses.dataclass(frozen=True)
class Nav2MapYaml:
    """The fields of a map YAML, checked. `image` is resolved against the YAML's folder."""

    path: Path
    image: Path
    resolution: float
    origin: tuple[float, float, float]
    negate: bool
    occupied_thresh: float
    free_thresh: float
    mode: str
    lines: dict = dataclasses.field(default_factory=dict, compare=False, repr=False)

    def error(self, field: str, problem: str) -> MapFormatError:
        """A MapFormatError naming this YAML file, the field's line (when known) and the field."""
        return MapFormatError(self.path, self.lines.get(field), f"field '{field}': {problem}")


@dataclasses.dataclass(frozen=True, eq=False)
class Nav2Map:
    """A map_server map downsampled to cells of `cell_size` metres.

    grid: uint8 (H, W), 1 = obstacle, row 0 = lowest y (OccupancyGrid order, see the module
    docstring); `Instance(grid, ...)` takes it as it is. origin_x, origin_y: metres of the grid's
    lower-left corner (the YAML's origin); yaw is always 0.0. pixels_per_cell: k, the cell's side
    in image pixels. source: the YAML file; meta: its checked fields.
    """

    grid: np.ndarray
    cell_size: float
    origin_x: float
    origin_y: float
    yaw: float
    pixels_per_cell: int
    source: Path
    meta: Nav2MapYaml

    @property
    def geometry(self) -> tuple[float, float, float]:
        """(resolution, origin_x, origin_y): the arguments of `fleet.topics.MapGeometry`."""
        return (self.cell_size, self.origin_x, self.origin_y)

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(int(v) for v in self.grid.shape)

    def cell_to_xy(self, row: int, col: int) -> tuple[float, float]:
        """Map-frame metres of the cell's centre (as MapGeometry.cell_to_xy)."""
        return (self.origin_x + (col + 0.5) * self.cell_size,
                self.origin_y + (row + 0.5) * self.cell_size)

    def xy_to_cell(self, x: float, y: float) -> tuple[int, int]:
        """The (row, col) containing (x, y) (as MapGeometry.xy_to_cell; may lie off the grid)."""
        return (int(math.floor((y - self.origin_y) / self.cell_size)),
                int(math.floor((x - self.origin_x) / self.cell_size)))

    def contains(self, row: int, col: int) -> bool:
        h, w = self.grid.shape
        return 0 <= row < h and 0 <= col < w


# --- the YAML ---------------------------------------------------------------------------------

def _key_lines(text: str) -> dict:
    """Top-level key -> 1-based line of the key, for error messages (best effort)."""
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return {}
    if not isinstance(node, yaml.MappingNode):
        return {}
    return {k.value: k.start_mark.line + 1 for k, _ in node.value if isinstance(k, yaml.ScalarNode)}


def _number(path, lines, data, field) -> float:
    value = data[field]
    # bool is an int in Python: "resolution: true" is a wrong type, not 1.0
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise MapFormatError(path, lines.get(field),
                             f"field '{field}': expected a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise MapFormatError(path, lines.get(field), f"field '{field}': {value!r} is not finite")
    return value


def read_nav2_yaml(yaml_path: str | PathLike) -> Nav2MapYaml:
    """The checked fields of a map_server YAML. MapFormatError (file, line, field) on: an unreadable
    file or bad YAML, a missing field, a wrong type, resolution <= 0, an origin that is not 3
    numbers, a threshold outside [0, 1], free_thresh >= occupied_thresh, an unknown mode. The image
    file itself is not opened here."""
    path = Path(yaml_path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise MapFormatError(path, None, f"cannot read the map YAML: {exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = None if mark is None else mark.line + 1
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise MapFormatError(path, line, f"not valid YAML: {problem}") from None
    if not isinstance(data, dict):
        raise MapFormatError(path, None, f"expected a mapping of map fields, got "
                                         f"{type(data).__name__}")
    lines = _key_lines(text)
    for field in _REQUIRED:
        if field not in data:
            raise MapFormatError(path, None, f"field '{field}' is missing (a map_server YAML has "
                                             f"{', '.join(_REQUIRED)} and optionally mode)")

    image = data["image"]
    if not isinstance(image, str) or not image.strip():
        raise MapFormatError(path, lines.get("image"),
                             f"field 'image': expected a file name, got {image!r}")
    image_path = Path(image)
    if not image_path.is_absolute():
        image_path = path.parent / image_path  # map_server: relative to the YAML's folder

    resolution = _number(path, lines, data, "resolution")
    if resolution <= 0:
        raise MapFormatError(path, lines.get("resolution"),
                             f"field 'resolution': must be > 0 metres per pixel, "
                             f"got {resolution!r}")

    origin = data["origin"]
    if (not isinstance(origin, list) or len(origin) != 3
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in origin)):
        raise MapFormatError(path, lines.get("origin"),
                             f"field 'origin': expected [x, y, yaw] (3 numbers), got {origin!r}")
    origin = tuple(float(v) for v in origin)
    if not all(math.isfinite(v) for v in origin):
        raise MapFormatError(path, lines.get("origin"),
                             f"field 'origin': {list(origin)} is not finite")

    negate = data["negate"]
    if isinstance(negate, bool):
        pass
    elif isinstance(negate, int) and negate in (0, 1):
        negate = bool(negate)
    else:
        raise MapFormatError(path, lines.get("negate"),
                             f"field 'negate': expected 0, 1, true or false, got {negate!r}")

    thresholds = {}
    for field in ("occupied_thresh", "free_thresh"):
        value = _number(path, lines, data, field)
        if not 0.0 <= value <= 1.0:
            raise MapFormatError(path, lines.get(field), f"field '{field}': must lie in [0, 1], "
                                                         f"got {value!r}")
        thresholds[field] = value
    if thresholds["free_thresh"] >= thresholds["occupied_thresh"]:
        raise MapFormatError(path, lines.get("free_thresh"),
                             f"field 'free_thresh': {thresholds['free_thresh']!r} must be below "
                             f"occupied_thresh {thresholds['occupied_thresh']!r}")

    mode = data.get("mode", "trinary")
    if mode not in MODES:  # map_server's map_mode_from_string takes these exact words
        raise MapFormatError(path, lines.get("mode"),
                             f"field 'mode': expected one of {', '.join(MODES)}, got {mode!r}")

    return Nav2MapYaml(path, image_path, resolution, origin, negate,
                       thresholds["occupied_thresh"], thresholds["free_thresh"], mode, lines)


# --- the image --------------------------------------------------------------------------------

def _read_pixels(meta: Nav2MapYaml) -> tuple[np.ndarray, np.ndarray | None]:
    """(shade_rgb (H, W) float64 in [0, 1]: the mean of R, G, B; alpha (H, W) in [0, 1] or None
    when the image has no alpha channel), in the picture's row order (row 0 = top)."""
    try:
        # Pillow only: it reads PGM (P2/P5) and PNG, and imageio's other plugins would only turn a
        # broken file into a longer message (and deprecation warnings)
        props = iio.immeta(meta.image, plugin="pillow")
        # a palette PNG: expand its palette, keeping a transparency entry as alpha
        mode = ("RGBA" if "transparency" in props else "RGB") if props.get("mode") == "P" else None
        pixels = iio.imread(meta.image, plugin="pillow", mode=mode)
    except Exception as exc:  # imageio raises OSError, ValueError, ... per backend
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise meta.error("image", f"cannot read image {meta.image} as PGM/PNG: {reason}") from None
    pixels = np.asarray(pixels)
    # Pillow scales a PGM's maxval to the full range of its mode (8 bit: 255, 16 bit: 65535), so
    # the dtype gives the full-scale value, as Magick's quantum scaling does.
    if pixels.dtype == bool:
        full = 1.0
    elif pixels.dtype == np.uint8:
        full = 255.0
    elif pixels.dtype in (np.uint16, np.int32) and pixels.min() >= 0 and pixels.max() <= 65535:
        full = 65535.0
    else:
        raise meta.error("image", f"image {meta.image} has unsupported pixels ({pixels.dtype}); "
                                  f"use an 8- or 16-bit grey or RGB(A) PGM/PNG")
    pixels = pixels.astype(np.float64) / full
    if pixels.ndim == 2:
        return pixels, None
    if pixels.ndim == 3 and pixels.shape[2] in (2, 3, 4) and pixels.shape[0] and pixels.shape[1]:
        channels = pixels.shape[2]
        colour = pixels[..., :1] if channels == 2 else pixels[..., :3]
        alpha = pixels[..., -1] if channels in (2, 4) else None
        return colour.mean(axis=2), alpha
    raise meta.error("image", f"image {meta.image} has shape {pixels.shape}, expected (H, W) "
                              f"grey, (H, W, 2) grey+alpha, (H, W, 3) RGB or (H, W, 4) RGBA")


def occupancy_values(meta: Nav2MapYaml) -> np.ndarray:
    """int8 (H_px, W_px) OccupancyGrid values (0 free, 100 occupied, -1 unknown, 1..99 in scale
    and raw modes) of the YAML's image, exactly as map_server computes them, in OccupancyGrid row
    order (row 0 = bottom of the picture)."""
    shade, alpha = _read_pixels(meta)
    if meta.mode == "trinary" and alpha is not None:
        shade = (3.0 * shade + alpha) / 4.0  # alpha averaged in as a 4th channel (map_server)
    occ = shade if meta.negate else 1.0 - shade
    lo, hi = meta.free_thresh, meta.occupied_thresh
    if meta.mode == "trinary":
        values = np.where(hi < occ, OCC_OCCUPIED, np.where(occ < lo, OCC_FREE, OCC_UNKNOWN))
    elif meta.mode == "scale":
        scaled = np.rint((occ - lo) / (hi - lo) * 100.0)
        values = np.where(hi < occ, OCC_OCCUPIED, np.where(occ < lo, OCC_FREE, scaled))
        if alpha is not None:
            values = np.where(alpha < 1.0, OCC_UNKNOWN, values)
    else:  # raw: the grey level itself, 0..100, anything above unknown
        level = np.round(shade * 255.0)
        values = np.where((level >= 0) & (level <= 100), level, OCC_UNKNOWN)
    return np.flipud(values.astype(np.int8))


def saver_unknown_read_as_free(meta: Nav2MapYaml) -> int:
    """How many pixels of map_saver's unknown grey (205) this YAML's thresholds read as FREE
    (a trinary map with free_thresh above 0.196, Nav2's default 0.25 among them): map_server
    reads them so too, while a user may expect unknown space to block."""
    if meta.mode != "trinary":
        return 0
    shade, alpha = _read_pixels(meta)
    grey = np.round(shade * 255.0) == SAVER_UNKNOWN
    if alpha is not None:
        grey &= alpha >= 1.0
    if not grey.any():
        return 0
    return int((grey & (np.flipud(occupancy_values(meta)) == OCC_FREE)).sum())


def pixels_per_cell(meta: Nav2MapYaml, cell_size: float | None) -> int:
    """k = cell_size / resolution as a whole number >= 1 (cell_size None: 1, one pixel a cell);
    MapFormatError naming the YAML's resolution field when cell_size is not a whole number of
    pixels."""
    if cell_size is None:
        return 1
    cell_size = float(cell_size)
    if not (math.isfinite(cell_size) and cell_size > 0):
        raise meta.error("resolution", f"cell_size must be a positive number of metres, got "
                                       f"{cell_size!r}")
    ratio = cell_size / meta.resolution
    k = round(ratio)
    if k < 1 or abs(ratio - k) > _PIXELS_TOLERANCE * max(1.0, ratio):
        raise meta.error("resolution", f"cell_size {cell_size!r} m is not a whole number of "
                                       f"{meta.resolution!r} m pixels ({ratio:.6g} pixels)")
    return int(k)


def downsample_blocked(blocked: np.ndarray, k: int) -> np.ndarray:
    """uint8 (ceil(H/k), ceil(W/k)): 1 where any pixel of the k x k block is blocked. Blocks start
    at row 0 / col 0 (the origin); the missing pixels of a partial last block count as blocked."""
    blocked = np.asarray(blocked, dtype=bool)
    h, w = blocked.shape
    hc, wc = -(-h // k), -(-w // k)
    padded = np.ones((hc * k, wc * k), dtype=bool)
    padded[:h, :w] = blocked
    return padded.reshape(hc, k, wc, k).any(axis=(1, 3)).astype(np.uint8)


def read_nav2_map(yaml_path: str | PathLike, cell_size: float | None = None) -> Nav2Map:
    """Load a Nav2 map_server map (YAML + PGM/PNG) as a grid of `cell_size`-metre cells
    (None: the map's resolution, one pixel a cell). Every problem with the files is one
    MapFormatError naming the YAML file and the field (`image` for an unreadable image)."""
    meta = read_nav2_yaml(yaml_path)
    if abs(meta.origin[2]) > _YAW_TOLERANCE:
        raise meta.error("origin", f"yaw {meta.origin[2]!r} is not supported (only 0: the grid's "
                                   f"cells are axis-aligned in the map frame)")
    k = pixels_per_cell(meta, cell_size)
    values = occupancy_values(meta)
    blocked = (values == OCC_UNKNOWN) | (values >= OCCUPIED_VALUE)
    grid = downsample_blocked(blocked, k)
    grid.setflags(write=False)
    return Nav2Map(grid, meta.resolution * k, meta.origin[0], meta.origin[1], 0.0, k, meta.path,
                   meta)


def write_nav2_map(yaml_path: str | PathLike, grid, cell_size: float,
                   origin=(0.0, 0.0, 0.0), image_format: str = "pgm") -> Path:
    """Write `grid` as map_saver does: `<yaml stem>.<image_format>` (8-bit grey, 254 free, 0
    occupied, 205 unknown) beside a trinary YAML (resolution cell_size, origin, negate 0,
    occupied_thresh 0.65, free_thresh 0.196). grid: (H, W) in OccupancyGrid row order (row 0 =
    lowest y, the order `read_nav2_map` returns), 0 free, 1 obstacle, -1 unknown. origin: (x, y)
    or (x, y, yaw). Returns the image's path. `read_nav2_map(yaml_path)` gives the grid back
    (unknown as obstacle)."""
    yaml_path = Path(yaml_path)
    grid = np.asarray(grid)
    if grid.ndim != 2 or 0 in grid.shape:
        raise ValueError(f"grid must be a non-empty 2-D array, got shape {grid.shape}")
    if not np.isin(grid, (-1, 0, 1)).all():
        raise ValueError("grid must hold only 0 (free), 1 (obstacle) and -1 (unknown)")
    if not (math.isfinite(float(cell_size)) and float(cell_size) > 0):
        raise ValueError(f"cell_size must be a positive number of metres, got {cell_size!r}")
    origin = [float(v) for v in origin]
    if len(origin) == 2:
        origin.append(0.0)
    if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
        raise ValueError(f"origin must be (x, y) or (x, y, yaw) finite numbers, got {origin!r}")
    if image_format not in ("pgm", "png"):
        raise ValueError(f"image_format must be 'pgm' or 'png', got {image_format!r}")
    pixels = np.full(grid.shape, SAVER_UNKNOWN, dtype=np.uint8)
    pixels[grid == 0] = SAVER_FREE
    pixels[grid == 1] = SAVER_OCCUPIED
    image_path = yaml_path.with_suffix("." + image_format)
    iio.imwrite(image_path, np.flipud(pixels))  # picture row 0 is the top (highest y)
    fields = {"image": image_path.name, "mode": "trinary", "resolution": float(cell_size),
              "origin": origin, "negate": 0, "occupied_thresh": WRITE_OCCUPIED_THRESH,
              "free_thresh": WRITE_FREE_THRESH}
    # floats written by repr (PyYAML), so the origin and resolution read back exactly
    yaml_path.write_text(yaml.safe_dump(fields, sort_keys=False, default_flow_style=None),
                         encoding="utf-8")
    return image_path


def load_grid_map(path: str | PathLike, cell_size: float | None = None
                  ) -> tuple[np.ndarray, tuple[float, float, float]]:
    """The project's map from either kind of file, for `--map F`: (grid uint8 (H, W), 1 =
    obstacle; (resolution, origin_x, origin_y) for `fleet.topics.MapGeometry`).
    `.yaml` / `.yml`: a Nav2 map_server map (`read_nav2_map`, cell_size None: its resolution).
    Anything else: a MovingAI .map (`movingai.read_map`), cells of cell_size metres (None: 1.0)
    with origin (0, 0), as the simulator's `resolution` parameter places them today."""
    path = Path(path)
    if path.suffix.lower() in (".yaml", ".yml"):
        nav2 = read_nav2_map(path, cell_size)
        return np.array(nav2.grid), nav2.geometry
    resolution = 1.0 if cell_size is None else float(cell_size)
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"cell_size must be a positive number of metres, got {cell_size!r}")
    return read_map(path), (resolution, 0.0, 0.0)
