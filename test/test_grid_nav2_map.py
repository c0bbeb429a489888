"""Nav2 map_server maps (YAML + PGM/PNG): pixel occupancy as map_server computes it, downsampling to
cells, rows and metres, malformed files, and the map_saver-style writer."""

import math

import imageio.v3 as iio
import numpy as np
import pytest
import yaml

from mapf_fleet.grid.errors import MapFormatError
from mapf_fleet.grid.instance import Instance
from mapf_fleet.grid.movingai import read_map, write_map
from mapf_fleet.grid.nav2_map import (load_grid_map, occupancy_values, read_nav2_map,
                                      read_nav2_yaml, write_nav2_map)
from mapf_fleet.ros.common import MapGeometry  # numpy only at import (no rclpy)

FIELDS = {"image": "map.pgm", "resolution": 0.5, "origin": [-1.0, 2.0, 0.0], "negate": 0,
          "occupied_thresh": 0.65, "free_thresh": 0.196}
W, B, U = 254, 0, 205  # map_saver's free, occupied, unknown grey


def _write(tmp_path, pixels, name="map.pgm", yaml_text=None, **fields):
    """Write `pixels` (picture order: row 0 = top) as `name` and a map YAML beside it; a field
    given as None is left out."""
    iio.imwrite(tmp_path / name, np.asarray(pixels, dtype=np.uint8))
    data = {**FIELDS, "image": name, **fields}
    data = {k: v for k, v in data.items() if v is not None}
    path = tmp_path / "map.yaml"
    path.write_text(yaml_text if yaml_text is not None else yaml.safe_dump(data, sort_keys=False))
    return path


# A 3 x 4 picture; as the grid (row 0 = bottom of the picture) it reads bottom-up.
PICTURE = [[W, W, B, W],
           [W, U, W, W],
           [B, W, W, W]]


def test_pgm_cells_resolution_origin(tmp_path):
    path = _write(tmp_path, PICTURE)
    assert (tmp_path / "map.pgm").read_bytes()[:2] == b"P5"  # a binary PGM, as map_saver writes
    m = read_nav2_map(path)
    assert m.grid.tolist() == [[1, 0, 0, 0],   # picture's bottom row
                               [0, 1, 0, 0],
                               [0, 0, 1, 0]]   # picture's top row
    assert m.grid.dtype == np.uint8 and m.shape == (3, 4)
    assert (m.cell_size, m.origin_x, m.origin_y, m.yaw) == (0.5, -1.0, 2.0, 0.0)
    assert m.pixels_per_cell == 1
    assert m.geometry == (0.5, -1.0, 2.0)
    assert m.source == path and m.meta.image == tmp_path / "map.pgm"
    Instance(m.grid, [[0, 1]], [[2, 3]]).validate()  # the grid is Instance-ready as it is


def test_rgb_png_shade_is_mean_of_channels(tmp_path):
    pixels = np.array([[[255, 0, 0], [255, 255, 0], [0, 0, 0], [255, 255, 255], [200, 200, 200]]],
                      dtype=np.uint8)
    path = _write(tmp_path, pixels, name="map.png", free_thresh=0.25)
    # shades 1/3, 2/3, 0, 1, 200/255 -> occ 0.667 (> 0.65 occupied), 0.333 (unknown), 1, 0, 0.216
    np.testing.assert_array_equal(occupancy_values(read_nav2_yaml(path)), [[100, -1, 100, 0, 0]])
    assert read_nav2_map(path).grid.tolist() == [[1, 1, 1, 0, 0]]


def test_rgba_trinary_averages_alpha_in_and_scale_marks_transparent_unknown(tmp_path):
    pixels = np.array([[[0, 0, 0, 255], [255, 255, 255, 0], [255, 255, 255, 255],
                        [128, 128, 128, 128]]], dtype=np.uint8)
    path = _write(tmp_path, pixels, name="map.png", free_thresh=0.25)
    # map_server (trinary, image with alpha): shade = (R + G + B + A) / 4: opaque black 0.25 ->
    # occ 0.75 occupied; transparent white 0.75 -> occ 0.25, not < 0.25: unknown
    assert occupancy_values(read_nav2_yaml(path)).tolist() == [[100, -1, 0, -1]]
    path = _write(tmp_path, pixels, name="map.png", free_thresh=0.25, mode="scale")
    # scale: colour only; a pixel that is not fully opaque is unknown
    assert occupancy_values(read_nav2_yaml(path)).tolist() == [[100, -1, 0, -1]]
    # occ 1 - 100/255 = 0.6078: rint((0.6078 - 0.25) / 0.4 * 100) = 89
    grey = np.array([[[100, 100, 100, 255]]], dtype=np.uint8)
    path = _write(tmp_path, grey, name="g.png", free_thresh=0.25, mode="scale")
    assert occupancy_values(read_nav2_yaml(path)).tolist() == [[89]]
    assert read_nav2_map(path).grid.tolist() == [[1]]  # 89 >= 50: an obstacle


def test_pgm_maxval_other_than_255_and_16_bit(tmp_path):
    # shade = value / maxval, as for any PGM: 0 -> occupied, maxval -> free, half -> unknown
    (tmp_path / "a.pgm").write_bytes(b"P5\n3 1\n100\n" + bytes([0, 100, 50]))
    (tmp_path / "b.pgm").write_bytes(b"P5\n3 1\n1000\n" + np.array([0, 1000, 500], ">u2").tobytes())
    for name in ("a.pgm", "b.pgm"):
        path = tmp_path / f"{name}.yaml"
        path.write_text(yaml.safe_dump({**FIELDS, "image": name}))
        assert occupancy_values(read_nav2_yaml(path)).tolist() == [[100, 0, -1]]


def test_palette_png_with_transparency(tmp_path):
    from PIL import Image  # imageio's backend; only to write a palette PNG here

    image = Image.new("P", (3, 1))
    image.putpalette([0, 0, 0, 255, 255, 255, 250, 250, 250])
    image.putdata([0, 1, 2])
    image.save(tmp_path / "p.png", transparency=1)
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump({**FIELDS, "image": "p.png", "free_thresh": 0.25}))
    # the palette's transparent white has alpha 0: shade (3 + 0) / 4 = 0.75, occ 0.25: unknown
    assert occupancy_values(read_nav2_yaml(path)).tolist() == [[100, -1, 0]]


def test_raw_mode_values(tmp_path):
    path = _write(tmp_path, [[0, 30, 100, 101, 255]], mode="raw")
    assert occupancy_values(read_nav2_yaml(path)).tolist() == [[0, 30, 100, -1, -1]]
    assert read_nav2_map(path).grid.tolist() == [[0, 0, 1, 1, 1]]


def test_trinary_thresholds_are_strict(tmp_path):
    ramp = np.arange(256, dtype=np.uint8)[None, :]
    path = _write(tmp_path, ramp)  # occupied 0.65, free 0.196
    values = occupancy_values(read_nav2_yaml(path))[0]
    # occ = 1 - v/255: > 0.65 for v <= 89; < 0.196 for v >= 206; grey 205 (occ 0.19608) unknown
    assert (values[:90] == 100).all() and (values[90:206] == -1).all() and (values[206:] == 0).all()
    # Nav2's default free_thresh 0.25 reads map_saver's unknown grey 205 as free (map_server too)
    path = _write(tmp_path, ramp, free_thresh=0.25)
    values = occupancy_values(read_nav2_yaml(path))[0]
    assert (values[90:192] == -1).all() and (values[192:] == 0).all() and values[205] == 0


def test_negate(tmp_path):
    path = _write(tmp_path, PICTURE, negate=1)
    # black is free, white (254: occ 0.996) occupied, 205 (occ 0.804) occupied too
    assert read_nav2_map(path).grid.tolist() == [[0, 1, 1, 1], [1, 1, 1, 1], [1, 1, 0, 1]]
    assert read_nav2_map(_write(tmp_path, PICTURE, negate=True)).grid.tolist() == \
        read_nav2_map(path).grid.tolist()


def test_downsampling_blocks_on_any_occupied_or_unknown_pixel_and_partial_edges(tmp_path):
    pixels = np.full((5, 5), W, dtype=np.uint8)  # picture order
    pixels[3, 2] = B  # picture rows 3-4 are the bottom block -> cell (0, 1)
    pixels[1, 0] = U  # picture rows 1-2 -> cell row 1, cols 0-1 -> cell (1, 0)
    path = _write(tmp_path, pixels, resolution=0.05)
    m = read_nav2_map(path, cell_size=0.1)
    assert m.pixels_per_cell == 2 and m.cell_size == pytest.approx(0.1)
    # 5 pixels -> 3 cells a side; the top row and the right column are partial: blocked
    assert m.grid.tolist() == [[0, 1, 1], [1, 0, 1], [1, 1, 1]]
    m3 = read_nav2_map(path, cell_size=0.15)  # 0.15 / 0.05 = 2.9999999999999996: 3 pixels
    assert m3.pixels_per_cell == 3 and m3.grid.tolist() == [[1, 1], [1, 1]]
    assert read_nav2_map(path, cell_size=0.25).grid.tolist() == [[1]]
    free = _write(tmp_path, np.full((4, 6), W, dtype=np.uint8), resolution=0.05)
    assert read_nav2_map(free, cell_size=0.1).grid.tolist() == [[0, 0, 0], [0, 0, 0]]


@pytest.mark.parametrize("cell_size", [0.07, 0.025, 0.0, -0.1, math.nan])
def test_cell_size_not_a_whole_number_of_pixels(tmp_path, cell_size):
    path = _write(tmp_path, PICTURE, resolution=0.05)
    with pytest.raises(MapFormatError, match=r"map\.yaml:\d+: field 'resolution': cell_size"):
        read_nav2_map(path, cell_size=cell_size)


def test_pose_in_metres_lands_in_its_cell(tmp_path):
    path = _write(tmp_path, PICTURE)
    m = read_nav2_map(path)
    geometry = MapGeometry(*m.geometry)
    # the picture's top-left pixel (free) is grid cell (2, 0): centre at the map's top
    assert m.grid[2, 0] == 0
    x, y = m.cell_to_xy(2, 0)
    assert (x, y) == (-1.0 + 0.25, 2.0 + 2.5 * 0.5)
    assert m.xy_to_cell(x, y) == (2, 0) and geometry.xy_to_cell(x, y) == (2, 0)
    for row, col in np.argwhere(m.grid == 0):
        assert geometry.cell_to_xy(row, col) == m.cell_to_xy(row, col)
        assert m.xy_to_cell(*m.cell_to_xy(row, col)) == (row, col)
    # the lower-left pixel's lower-left corner is the origin; a point just inside it is cell (0, 0)
    assert m.xy_to_cell(-1.0 + 1e-9, 2.0 + 1e-9) == (0, 0)
    assert m.xy_to_cell(-1.0 - 1e-9, 2.0) == (0, -1) and not m.contains(0, -1)


def _error(path, **kwargs) -> str:
    with pytest.raises(MapFormatError) as info:
        read_nav2_map(path, **kwargs)
    text = str(info.value)
    assert "\n" not in text and str(path) in text and info.value.file == str(path)
    return text


@pytest.mark.parametrize("field", ["image", "resolution", "origin", "negate", "occupied_thresh",
                                   "free_thresh"])
def test_missing_field(tmp_path, field):
    assert f"field '{field}' is missing" in _error(_write(tmp_path, PICTURE, **{field: None}))


@pytest.mark.parametrize("field, value, words", [
    ("image", 5, "expected a file name"),
    ("image", "", "expected a file name"),
    ("resolution", "fine", "expected a number"),
    ("resolution", True, "expected a number"),
    ("resolution", 0, "must be > 0"),
    ("resolution", math.inf, "not finite"),
    ("origin", [0.0, 0.0], "expected [x, y, yaw]"),
    ("origin", "0 0 0", "expected [x, y, yaw]"),
    ("origin", [0.0, 0.0, 0.5], "yaw 0.5 is not supported"),
    ("negate", 2, "expected 0, 1, true or false"),
    ("negate", "no", "expected 0, 1, true or false"),
    ("occupied_thresh", 1.5, "must lie in [0, 1]"),
    ("free_thresh", -0.1, "must lie in [0, 1]"),
    ("occupied_thresh", "high", "expected a number"),
    ("free_thresh", 0.65, "must be below occupied_thresh"),
    ("mode", "Trinary", "expected one of trinary, scale, raw"),
    ("mode", "binary", "expected one of trinary, scale, raw"),
])
def test_bad_field(tmp_path, field, value, words):
    path = _write(tmp_path, PICTURE, **{field: value})
    text = _error(path)
    assert f"field '{field}'" in text and words in text
    line = 1 + [k.split(":")[0] for k in path.read_text().splitlines()].index(field)
    assert text.startswith(f"{path}:{line}: ")  # the line of the field at fault


def test_missing_or_unreadable_image(tmp_path):
    path = _write(tmp_path, PICTURE, image="elsewhere.pgm")
    text = _error(path)
    assert "field 'image'" in text and "elsewhere.pgm" in text
    (tmp_path / "broken.pgm").write_bytes(b"P5\n4 3\n255\n\x00")  # truncated pixel data
    text = _error(_write(tmp_path, PICTURE, image="broken.pgm"))
    assert "field 'image'" in text and "broken.pgm" in text
    (tmp_path / "junk.png").write_bytes(b"not an image at all")
    assert "field 'image'" in _error(_write(tmp_path, PICTURE, image="junk.png"))


def test_image_relative_to_the_yaml_not_the_working_directory(tmp_path, monkeypatch):
    sub = tmp_path / "maps"
    sub.mkdir()
    path = _write(sub, PICTURE)
    monkeypatch.chdir(tmp_path)
    assert read_nav2_map("maps/map.yaml").grid.shape == (3, 4)
    absolute = _write(tmp_path, PICTURE, image=str(sub / "map.pgm"))
    assert read_nav2_map(absolute).grid.tolist() == read_nav2_map(path).grid.tolist()


def test_not_a_yaml_mapping_or_no_file(tmp_path):
    assert "not valid YAML" in _error(_write(tmp_path, PICTURE, yaml_text="image: [unclosed\n"))
    assert "expected a mapping" in _error(_write(tmp_path, PICTURE, yaml_text="- a\n- b\n"))
    assert "cannot read the map YAML" in _error(tmp_path / "absent.yaml")


def test_write_read_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    grid = rng.choice([-1, 0, 0, 0, 1], size=(7, 9))
    image = write_nav2_map(tmp_path / "out.yaml", grid, 0.25, origin=(-3.125, 4.5))
    assert image == tmp_path / "out.pgm"
    header_and_pixels = image.read_bytes()
    assert header_and_pixels.startswith(b"P5") and header_and_pixels.endswith(
        np.flipud(np.select([grid == 0, grid == 1], [254, 0], 205)).astype(np.uint8).tobytes())
    fields = yaml.safe_load((tmp_path / "out.yaml").read_text())
    assert fields == {"image": "out.pgm", "mode": "trinary", "resolution": 0.25,
                      "origin": [-3.125, 4.5, 0.0], "negate": 0, "occupied_thresh": 0.65,
                      "free_thresh": 0.196}
    m = read_nav2_map(tmp_path / "out.yaml")
    np.testing.assert_array_equal(m.grid, (grid != 0).astype(np.uint8))  # unknown -> obstacle
    assert m.geometry == (0.25, -3.125, 4.5)
    np.testing.assert_array_equal(occupancy_values(m.meta),
                                  np.select([grid == 0, grid == 1], [0, 100], -1))
    write_nav2_map(tmp_path / "png.yaml", grid, 0.25, image_format="png")
    np.testing.assert_array_equal(read_nav2_map(tmp_path / "png.yaml").grid, m.grid)


def test_movingai_map_to_nav2_and_load_grid_map(tmp_path):
    grid = np.zeros((4, 6), dtype=np.uint8)
    grid[1, 2:5] = 1
    write_map(tmp_path / "m.map", grid)
    write_nav2_map(tmp_path / "m.yaml", read_map(tmp_path / "m.map"), 0.5, origin=(1.0, -2.0, 0.0))
    loaded, geometry = load_grid_map(tmp_path / "m.yaml")
    np.testing.assert_array_equal(loaded, grid)
    assert geometry == (0.5, 1.0, -2.0)
    loaded, geometry = load_grid_map(tmp_path / "m.map", cell_size=0.5)
    np.testing.assert_array_equal(loaded, grid)
    assert geometry == (0.5, 0.0, 0.0)
    assert load_grid_map(tmp_path / "m.map")[1] == (1.0, 0.0, 0.0)
    with pytest.raises(MapFormatError, match="field 'resolution'"):
        load_grid_map(tmp_path / "m.yaml", cell_size=0.3)


@pytest.mark.parametrize("grid, kwargs, words", [
    (np.zeros((0, 3)), {}, "non-empty 2-D"),
    (np.full((2, 2), 2), {}, "only 0"),
    (np.zeros((2, 2)), {"cell_size": 0.0}, "cell_size"),
    (np.zeros((2, 2)), {"origin": (0.0,)}, "origin"),
    (np.zeros((2, 2)), {"image_format": "jpg"}, "image_format"),
])
def test_write_refuses_bad_arguments(tmp_path, grid, kwargs, words):
    kwargs = {"cell_size": 1.0, **kwargs}
    with pytest.raises(ValueError, match=words):
        write_nav2_map(tmp_path / "w.yaml", grid, **kwargs)
