"""MovingAI .map/.scen reading, writing, round trip and malformed files."""

import numpy as np
import pytest

from mapf_fleet.grid.errors import MapFormatError
from mapf_fleet.grid.instance import generate_instance
from mapf_fleet.grid.movingai import (ScenarioEntry, instance_to_scenario, load_movingai_instances,
                                      read_map, read_scen, write_map, write_scen)

MAP_TEXT = """type octile
height 3
width 4
map
..@.
.T..
G..S
"""


def test_read_map_characters(tmp_path):
    path = tmp_path / "small.map"
    path.write_text(MAP_TEXT)
    grid = read_map(path)
    assert grid.tolist() == [[0, 0, 1, 0], [0, 1, 0, 0], [0, 0, 0, 0]]
    assert grid.dtype == np.uint8


def test_instance_round_trip(tmp_path):
    inst = generate_instance(24, 10, 0.3, 7)
    write_map(tmp_path / "r.map", inst.grid)
    write_scen(tmp_path / "r.scen", instance_to_scenario(inst, "r.map", bucket=3))
    np.testing.assert_array_equal(read_map(tmp_path / "r.map"), inst.grid)
    entries = read_scen(tmp_path / "r.scen")
    assert len(entries) == 10 and entries[0].bucket == 3 and entries[0].map_name == "r.map"
    assert entries[0].start == tuple(inst.starts[0]) and entries[0].optimal_length > 0
    loaded = load_movingai_instances(tmp_path / "r.map", tmp_path / "r.scen", 10)
    assert loaded == inst
    assert load_movingai_instances(tmp_path / "r.map", tmp_path / "r.scen", 4).num_agents == 4


def test_scen_uses_x_column_y_row(tmp_path):
    path = tmp_path / "a.scen"
    path.write_text("version 1\n0\tm.map\t4\t3\t3\t1\t0\t2\t5.5\n")
    (entry,) = read_scen(path)
    assert entry == ScenarioEntry(0, "m.map", 4, 3, (1, 3), (2, 0), 5.5)


@pytest.mark.parametrize("text,line,words", [
    ("type octile\nheight 3\nwidth 4\nmap\n..@.\n.X..\nG..S\n", 6, "unknown map character 'X'"),
    ("type octile\nheight 3\nwidth 4\nmap\n..@.\n.T.\nG..S\n", 6, "row has 3 characters"),
    ("type octile\nheight 3\nwidth 4\nmap\n..@.\n.T..\n", 7, "expected 3 map rows, found 2"),
    ("type octile\nheight three\nwidth 4\nmap\n", 2, "height 'three' is not an integer"),
    ("type octile\nwidth 4\nheight 3\nmap\n", 2, "expected 'height ...'"),
    ("type octile\nheight 3\n", 3, "file ends before the 'width' header line"),
])
def test_malformed_map_names_file_line_problem(tmp_path, text, line, words):
    path = tmp_path / "bad.map"
    path.write_text(text)
    with pytest.raises(MapFormatError) as err:
        read_map(path)
    assert err.value.line == line and err.value.file == str(path)
    assert words in str(err.value) and str(err.value).startswith(f"{path}:{line}: ")


@pytest.mark.parametrize("text,line,words", [
    ("vers 1\n", 1, "expected a 'version 1' header"),
    ("version 2\n", 1, "unsupported scenario version"),
    ("version 1\n0\tm.map\t4\t3\t3\t1\t0\t2\n", 2, "expected 9 fields, found 8"),
    ("version 1\n0\tm.map\t4\t3\t3\t1\t0\t2\t1\n0\tm.map\t4\t3\tx\t1\t0\t2\t1\n", 3,
     "non-numeric field"),
    ("version 1\n\n0\tm.map\t4\t3\t4\t1\t0\t2\t1\n", 3, "start (x=4, y=1) is outside the 4x3 map"),
])
def test_malformed_scen_names_file_line_problem(tmp_path, text, line, words):
    path = tmp_path / "bad.scen"
    path.write_text(text)
    with pytest.raises(MapFormatError) as err:
        read_scen(path)
    assert err.value.line == line and words in str(err.value)
    assert str(err.value).startswith(f"{path}:{line}: ")


def test_load_movingai_mismatch_and_too_few_agents(tmp_path):
    (tmp_path / "m.map").write_text(MAP_TEXT)
    (tmp_path / "m.scen").write_text("version 1\n0\tm.map\t5\t3\t0\t0\t1\t0\t1\n")
    with pytest.raises(MapFormatError, match="entry 0 is for a 5x3 map"):
        load_movingai_instances(tmp_path / "m.map", tmp_path / "m.scen", 1)
    with pytest.raises(MapFormatError, match="asked for 2 agents, the file has 1 entries"):
        load_movingai_instances(tmp_path / "m.map", tmp_path / "m.scen", 2)


def test_non_ascii_file(tmp_path):
    path = tmp_path / "u.map"
    path.write_bytes(b"type octile\nheight 1\nwidth 1\nmap\n\xc3\xa9\n")
    with pytest.raises(MapFormatError, match=r"u\.map:5: non-ASCII"):
        read_map(path)
