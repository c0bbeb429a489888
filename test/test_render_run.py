"""`mapf-fleet render --run`: a fleet's recorded run (the JSON record of `up --record`, or a
rosbag2 of `mapf-fleet record` / `up --bag`) as GIF / WebP frames, without ROS (the bag here is
written with rosbags and the fleet's message definitions, as `mapf-fleet record` writes it)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from mapf_fleet.cli import main as mapf_fleet
from mapf_fleet.grid.instance import generate_instance
from mapf_fleet.view.replay import RunFileError, load_bag, load_record

SIZE, ROBOTS, SEED = 8, 2, 1


def _walk(instance, ticks=6):
    """A trajectory from the starts that ends on the goals (render checks cells, not moves)."""
    starts, goals = np.asarray(instance.starts), np.asarray(instance.goals)
    return [starts.tolist()] * (ticks - 1) + [goals.tolist()]


def _frames(path) -> int:
    with Image.open(path) as image:
        return image.n_frames


def _record(tmp_path, **fields):
    instance = generate_instance(SIZE, ROBOTS, 0.3, SEED)
    record = {"episode": 5, "positions": _walk(instance), "goals": instance.goals.tolist(),
              **fields}
    path = tmp_path / "run.json"
    path.write_text(json.dumps(record))
    return instance, path


def test_a_json_record_with_the_runs_instance_options(tmp_path, capsys):
    _, path = _record(tmp_path)
    out = tmp_path / "run.gif"
    args = ["render", "--run", str(path), "--size", str(SIZE), "--seed", str(SEED)]
    assert mapf_fleet(args + ["--out", str(out)]) == 0
    assert _frames(out) == 6
    assert "6 frames (ticks 0-5) of 2 robots on a 8x8 map" in capsys.readouterr().out
    assert mapf_fleet(args + ["--out", str(tmp_path / "run.webp")]) == 0
    assert _frames(tmp_path / "run.webp") == 6


def test_the_wrong_instance_is_named_not_drawn(tmp_path, capsys):
    _, path = _record(tmp_path)
    out = tmp_path / "run.gif"
    assert mapf_fleet(["render", "--run", str(path), "--size", str(SIZE), "--seed", "99",
                       "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"mapf-fleet render: {path}: the record's first cells are not the "
                          f"starts of the instance --size {SIZE} --density 0.3 --seed 99")
    assert len(err.strip().splitlines()) == 1 and not out.exists()


def test_goals_given_during_the_run_and_the_fleets_count(tmp_path):
    instance, path = _record(tmp_path, goal_events=[
        {"tick": 3, "robot": 1, "event": "assigned", "cell": [0, 0], "source": "external"},
        {"tick": 4, "robot": 0, "event": "reached", "cell": None, "source": "instance"},
        {"tick": 5, "robot": 1, "event": "reached", "cell": None, "source": "instance"}])
    run = load_record(path, {"size": SIZE, "seed": SEED})
    assert run.goals[2].tolist() == instance.goals.tolist()
    assert run.goals[3].tolist() == [instance.goals[0].tolist(), [0, 0]]
    assert run.reached == [0, 0, 0, 0, 1, 2]
    np.testing.assert_array_equal(run.grid, instance.grid)


def test_a_record_with_its_own_grid_needs_no_options(tmp_path):
    grid = ["....", ".@@.", "...."]
    path = tmp_path / "run.json"
    path.write_text(json.dumps({"episode": 1, "grid": grid, "goals": [[2, 3]],
                                "positions": [[[0, 0]], [[0, 1]], [[0, 2]]]}))
    run = load_record(path, {})
    assert run.grid.tolist() == [[0, 0, 0, 0], [0, 1, 1, 0], [0, 0, 0, 0]]
    assert run.goals.shape == (3, 1, 2) and run.reached is None
    path.write_text(json.dumps({"grid": grid, "goals": [[2, 3]], "positions": [[[5, 0]]]}))
    with pytest.raises(RunFileError, match="field 'positions' has cells off the 3x4 map"):
        load_record(path, {})
    path.write_text("{not json")
    with pytest.raises(RunFileError, match="not a JSON run record"):
        load_record(path, {})


def _write_bag(folder, instance, runs):
    """A rosbag2 (MCAP) like `mapf-fleet record`'s: the latched map, then per run its states
    and progress (`runs`: episode -> list of cells per tick)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from mapf_fleet.ros.bag import fleet_typestore

    store = fleet_typestore()
    T = store.types
    grid_msg = T["nav_msgs/msg/OccupancyGrid"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
                                        frame_id="map"),
        info=T["nav_msgs/msg/MapMetaData"](
            map_load_time=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), resolution=1.0,
            width=SIZE, height=SIZE, origin=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))),
        data=(np.asarray(instance.grid, np.int8).reshape(-1) * 100).astype(np.int8))
    stamp = 1_000
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        topics = {}
        for topic, kind in (("/fleet/map", "nav_msgs/msg/OccupancyGrid"),
                            ("/fleet/state", "mapf_fleet_interfaces/msg/FleetState")):
            topics[topic] = writer.add_connection(topic, kind, typestore=store)
        writer.write(topics["/fleet/map"], stamp,
                     store.serialize_cdr(grid_msg, "nav_msgs/msg/OccupancyGrid"))
        goals = np.asarray(instance.goals)
        for episode, cells in runs.items():
            for tick, at in enumerate(cells):
                at = np.asarray(at)
                state = T["mapf_fleet_interfaces/msg/FleetState"](
                    header=grid_msg.header, episode=episode, tick=tick,
                    rows=at[:, 0].astype(np.int32), cols=at[:, 1].astype(np.int32),
                    goal_rows=goals[:, 0].astype(np.int32), goal_cols=goals[:, 1].astype(np.int32),
                    last_actions=np.zeros(len(at), np.int8), done=tick == len(cells) - 1)
                stamp += 1_000
                writer.write(topics["/fleet/state"], stamp,
                             store.serialize_cdr(state, "mapf_fleet_interfaces/msg/FleetState"))


def test_a_rosbag_the_last_run_or_the_one_asked_for(tmp_path, capsys):
    instance = generate_instance(SIZE, ROBOTS, 0.3, SEED)
    walk = _walk(instance)
    bag = tmp_path / "bag"
    _write_bag(bag, instance, {7: walk[:3], 8: walk})
    run = load_bag(bag)
    assert run.episode == 8 and run.ticks == list(range(6))
    assert run.positions.tolist() == walk and run.goals[0].tolist() == instance.goals.tolist()
    np.testing.assert_array_equal(run.grid, instance.grid)
    assert load_bag(bag, episode=7).positions.tolist() == walk[:3]
    with pytest.raises(RunFileError, match="no states of episode 9 .episodes: 7, 8."):
        load_bag(bag, episode=9)
    with pytest.raises(RunFileError, match="no /fleet_a/fleet/state messages"):
        load_bag(bag, namespace="/fleet_a")
    out = tmp_path / "bag.gif"
    capsys.readouterr()
    assert mapf_fleet(["render", "--run", str(bag), "--namespace", "/wrong", "--out",
                       str(out)]) == 2
    err = capsys.readouterr().err
    assert "no /wrong/fleet/state messages" in err and len(err.strip().splitlines()) == 1
    assert mapf_fleet(["render", "--run", str(bag), "--out", str(out), "--fps", "4"]) == 0
    assert _frames(out) == 6


def test_mp4_needs_imageio_ffmpeg_and_says_so(tmp_path, capsys):
    try:
        import imageio_ffmpeg  # noqa: F401
        pytest.skip("imageio-ffmpeg is installed here: MP4 works")
    except ImportError:
        pass
    _, path = _record(tmp_path)
    assert mapf_fleet(["render", "--run", str(path), "--size", str(SIZE), "--seed", str(SEED),
                       "--out", str(tmp_path / "run.mp4")]) == 2
    assert "MP4 needs the optional imageio-ffmpeg" in capsys.readouterr().err


def test_render_help_names_the_recorded_run(capsys):
    with pytest.raises(SystemExit):
        mapf_fleet(["render", "--help"])
    assert "--run F.json|BAG_DIR" in capsys.readouterr().out


def test_a_nav2_map_run_redraws_with_its_cell_size(tmp_path, capsys):
    """`up --map building.yaml --cell-size 0.5` records no map: render takes the same
    --map and --cell-size (without --cell-size the map is one cell per pixel: refused)."""
    from mapf_fleet.grid.nav2_map import write_nav2_map
    from mapf_fleet.fleet.instances import InstanceSource

    pixels = np.zeros((8, 12), dtype=np.int64)
    pixels[2:4, 4:6] = 1
    yaml_path = tmp_path / "building.yaml"
    write_nav2_map(yaml_path, pixels, 0.25)
    instance = InstanceSource(map_file=str(yaml_path), num_robots=2, seed=1,
                              cell_size=0.5).load()
    record = {"positions": [np.asarray(instance.starts).tolist()],
              "goals": np.asarray(instance.goals).tolist()}
    path = tmp_path / "run.json"
    path.write_text(json.dumps(record))
    args = ["render", "--run", str(path), "--map", str(yaml_path), "--seed", "1",
            "--out", str(tmp_path / "run.gif")]
    assert mapf_fleet(args + ["--cell-size", "0.5"]) == 0
    assert "on a 4x6 map" in capsys.readouterr().out
    assert mapf_fleet(args) == 2
