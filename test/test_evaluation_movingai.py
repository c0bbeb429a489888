"""MovingAI input of `mapf-fleet evaluate`: several maps each with its own .scen (pairs in order,
folders, grouping by the map a .scen names), and errors that name the files: a .scen of another
map, a goal on an obstacle."""

import json

import numpy as np
import pytest

from mapf_fleet.cli import main as mapf_fleet
from mapf_fleet.evaluation.policies import parse_policy
from mapf_fleet.evaluation.protocol import InstanceSet, Scenario
from mapf_fleet.evaluation.runner import evaluate
from mapf_fleet.grid.errors import MapFormatError
from mapf_fleet.grid.instance import Instance, generate_instance
from mapf_fleet.grid.movingai import instance_to_scenario, load_movingai_instances, write_map, write_scen


@pytest.fixture
def bench(tmp_path):
    """maps/a.map (two .scen files) and maps/b.map (one), 12x12, 4 agents each."""
    (tmp_path / "maps").mkdir()
    (tmp_path / "scens").mkdir()
    instances = {}
    for name, seed in (("a", 1), ("b", 2)):
        base = generate_instance(12, 4, 0.25, np.random.default_rng(seed))
        write_map(tmp_path / "maps" / f"{name}.map", base.grid)
        instances[name] = [base]
        write_scen(tmp_path / "scens" / f"{name}-1.scen", instance_to_scenario(base, f"{name}.map"))
    free = np.argwhere(instances["a"][0].grid == 0)
    picks = free[np.random.default_rng(5).choice(len(free), 8, replace=False)]
    second = Instance(instances["a"][0].grid, picks[:4], picks[4:]).validate()
    write_scen(tmp_path / "scens" / "a-2.scen", instance_to_scenario(second, "a.map"))
    instances["a"].append(second)
    return tmp_path, instances


def _run(*args):
    return mapf_fleet(["evaluate", "--checkpoint", "heuristic", "--no-references",
                       "--conflict-rule", "revert", "--agents", "4",
                       "--quiet", *map(str, args)])


def _episodes(path):
    rows = json.loads(path.read_text())["results"]
    return {r["map"]: r["episodes"] for r in rows}


def test_several_maps_pair_with_their_scen_in_order(bench):
    tmp, instances = bench
    out = tmp / "pairs.json"
    assert _run("--map", tmp / "maps/a.map", tmp / "maps/b.map",
                "--scen", tmp / "scens/a-1.scen", tmp / "scens/b-1.scen", "--json", out) == 0
    got = _episodes(out)
    assert sorted(got) == ["a", "b"] and all(len(e) == 1 for e in got.values())
    heuristic = parse_policy("heuristic")
    for name in ("a", "b"):
        direct = evaluate([heuristic], [(Scenario(name, 4, 256), InstanceSet.from_instances(instances[name][:1], "d"))])
        assert got[name] == [e.to_dict() for e in direct[0].episodes]


def test_folders_group_each_scen_with_the_map_it_names(bench):
    tmp, instances = bench
    out = tmp / "folders.json"
    assert _run("--map", tmp / "maps", "--scen", tmp / "scens", "--json", out) == 0
    got = _episodes(out)
    assert {k: len(v) for k, v in got.items()} == {"a": 2, "b": 1}
    direct = evaluate([parse_policy("heuristic")], [(Scenario("a", 4, 256), InstanceSet.from_instances(instances["a"], "d"))])
    assert got["a"] == [e.to_dict() for e in direct[0].episodes]


def test_swapped_pairs_name_both_files(bench, capsys):
    tmp, _ = bench
    assert _run("--map", tmp / "maps/a.map", tmp / "maps/b.map",
                "--scen", tmp / "scens/b-1.scen", tmp / "scens/a-1.scen") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "b-1.scen" in err and "a.map" in err and "'b.map'" in err and "obstacle" not in err


def test_scen_of_another_map_is_refused_by_the_loader(bench):
    """Before: a .scen of another map of the same size loaded, or failed with 'start is on an
    obstacle' without naming either file."""
    tmp, _ = bench
    with pytest.raises(MapFormatError) as err:
        load_movingai_instances(tmp / "maps/a.map", tmp / "scens/b-1.scen", 4)
    text = str(err.value)
    assert text.startswith(f"{tmp / 'scens/b-1.scen'}:2: ") and "'b.map'" in text and str(tmp / "maps/a.map") in text


def test_goal_on_obstacle_names_the_scen_file_and_line(tmp_path):
    grid = np.zeros((6, 6), dtype=np.uint8)
    grid[4, 5] = 1
    write_map(tmp_path / "m.map", grid)
    # agent 1's goal is x=5, y=4: the obstacle
    (tmp_path / "m.scen").write_text("version 1\n0\tm.map\t6\t6\t0\t0\t1\t0\t1\n0\tm.map\t6\t6\t0\t2\t5\t4\t7\n")
    with pytest.raises(MapFormatError) as err:
        load_movingai_instances(tmp_path / "m.map", tmp_path / "m.scen", 2)
    text = str(err.value)
    assert text.startswith(f"{tmp_path / 'm.scen'}:3: agent 1, cell (row=4, col=5): goal is on an obstacle")
    assert "x=5, y=4" in text and str(tmp_path / "m.map") in text


def test_bad_multi_map_input_is_one_line_exit_2(bench, capsys):
    tmp, _ = bench
    cases = [
        (["--map", tmp / "maps/a.map", tmp / "maps/b.map", "--scen", tmp / "scens/a-1.scen", tmp / "scens/a-2.scen",
          tmp / "scens/a-1.scen"], "no .scen file names the map(s) "),
        (["--map", tmp / "maps/a.map", tmp / "nothing.map", "--scen", tmp / "scens/a-1.scen"], "nothing.map"),
        (["--map", tmp / "scens", "--scen", tmp / "scens/a-1.scen"], "no .map file in folder"),
        (["--map", tmp / "maps", "--scen", tmp / "scens/a-1.scen", tmp / "scens/a-2.scen", tmp / "scens/b-1.scen",
          tmp / "maps/a.map"], "a.map:1: expected a 'version 1' header"),
    ]
    (tmp / "other.scen").write_text("version 1\n0\tc.map\t12\t12\t0\t0\t1\t0\t1\n")
    cases.append((["--map", tmp / "maps", "--scen", tmp / "other.scen"], "'c.map'"))
    for args, needle in cases:
        assert _run(*args) == 2, args
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and needle in err, (args, err)
