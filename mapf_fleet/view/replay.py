"""`mapf-fleet render --run RUN --out F.gif`: a fleet's recorded run as an animation to share.

    mapf-fleet render --run run.json --out run.gif               # `up --record run.json`
    mapf-fleet render --run run.json --size 10 --seed 2 --out run.gif
    mapf-fleet render --run bags/run1 --out run.webp             # `record` / `up --bag` rosbag2

RUN is either
- the JSON record of `up --record` (or the node's record_file): the trajectory (`positions`), the
  first goals and every goal change (`goal_events`) of the run. It holds no map unless it has a
  `grid` field, so give render the instance options the run was started with (--instance, --map
  [--scen], or --size/--density/--seed as for `up`; --num-robots comes from the record); the
  record's first cells must be that instance's starts, else render says so;
- a rosbag2 directory (or its .mcap file) holding /fleet/map and /fleet/state (`mapf-fleet
  record`, `up --bag`): map, cells and goals of every tick, read with the bag's own message
  definitions (rosbags' AnyReader), so bags of older message versions still read. A bag with
  several runs: the last one, or --episode. A bag whose recorder was killed (no metadata.yaml)
  is read up to its last complete tick (`view.bag_salvage`), and a bag that ends without the
  run's outcome (/fleet/outcome) is rendered as far as it goes, with a line saying so.

Frames: `evaluation.render.draw_frames` (as `render --checkpoint`'s episodes), with the paths
taken, the goals as they change, and per frame the robots on goal, the goals reached and the
throughput (goals per tick), counted by `view.picture.FleetPicture` as the live view counts them
(the fleet's own count when the record or the bag carries it). The output format follows --out
(`evaluation.render.save_frames`: .gif, .webp, .mp4 with imageio-ffmpeg, else PNG frames).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapf_fleet.grid.errors import MapFormatError


class RunFileError(ValueError):
    """A recorded run cannot be read (the message names the file, the field and the problem)."""


@dataclass
class RecordedRun:
    grid: np.ndarray          # (H, W) 1 = obstacle
    ticks: list[int]          # the tick of each frame
    positions: np.ndarray     # (T, N, 2)
    goals: np.ndarray         # (T, N, 2): each frame's goals
    reached: list | None      # per frame: the fleet's goals reached so far (None: not recorded)
    episode: int
    label: str
    notes: list = field(default_factory=list)  # what the reader had to say (one line each)


# ---- the JSON record ----------------------------------------------------------------------------
def _grid_field(path, value) -> np.ndarray:
    if isinstance(value, list) and value and all(isinstance(r, str) for r in value):
        from mapf_fleet.fleet.instances import FREE_CHARS, OBSTACLE_CHARS

        bad = sorted({ch for row in value for ch in row} - FREE_CHARS - OBSTACLE_CHARS)
        if bad or len({len(r) for r in value}) != 1:
            raise RunFileError(f"{path}: field 'grid': rows of one length of "
                               f"{''.join(sorted(FREE_CHARS | OBSTACLE_CHARS))} expected")
        return np.array([[ch in OBSTACLE_CHARS for ch in row] for row in value], np.uint8)
    grid = np.asarray(value)
    if grid.ndim != 2 or grid.size == 0:
        raise RunFileError(f"{path}: field 'grid' must be row strings or a 2-D list")
    return (grid != 0).astype(np.uint8)


def load_record(path, instance_options: dict) -> RecordedRun:
    """A JSON run record; the map from its `grid` field, else from `instance_options`
    (fleet.instances.InstanceSource fields)."""
    path = Path(path)
    from mapf_fleet.fleet.record import read_record

    try:  # with the ticks a killed fleet left in its journal
        record = read_record(path)
    except FileNotFoundError:
        raise RunFileError(f"{path}: no such file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RunFileError(f"{path}: not a JSON run record ({exc})") from None
    if not isinstance(record, dict) or not isinstance(record.get("positions"), list) \
            or not record["positions"]:
        raise RunFileError(f"{path}: field 'positions' (the run's cells per tick) missing or empty")
    try:
        positions = np.asarray(record["positions"], dtype=np.int64)
    except (ValueError, TypeError):
        positions = None
    if positions is None or positions.ndim != 3 or positions.shape[2] != 2:
        raise RunFileError(f"{path}: field 'positions' must be ticks x robots x (row, col)")
    frames, n = positions.shape[:2]
    instance = None
    if "grid" in record:
        grid = _grid_field(path, record["grid"])
    else:
        from mapf_fleet.fleet.instances import InstanceSource

        try:
            instance = InstanceSource(num_robots=n, **instance_options).load()
        except (ValueError, FileNotFoundError, MapFormatError) as exc:
            raise RunFileError(f"{path}: the record holds no map and the instance options "
                               f"give none: {exc}") from None
        if instance.num_agents != n or not np.array_equal(instance.starts, positions[0]):
            raise RunFileError(
                f"{path}: the record's first cells are not the starts of the instance "
                f"{_describe(instance_options)}: give render the options of the `up` run "
                "(--instance, --map/--scen, or --size/--density/--seed)")
        grid = instance.grid
    h, w = grid.shape
    if (positions < 0).any() or (positions[..., 0] >= h).any() or (positions[..., 1] >= w).any():
        raise RunFileError(f"{path}: field 'positions' has cells off the {h}x{w} map")
    if "goals" in record:
        first = np.asarray(record["goals"], dtype=np.int64).reshape(-1, 2)
    elif instance is not None:
        first = np.asarray(instance.goals, dtype=np.int64)
    else:
        raise RunFileError(f"{path}: field 'goals' missing")
    if first.shape != (n, 2):
        raise RunFileError(f"{path}: field 'goals' has {len(first)} goals for {n} robots")
    goals = np.repeat(first[None], frames, axis=0)
    reached_at = []
    for k, event in enumerate(record.get("goal_events", [])):
        try:
            tick, robot, kind = int(event["tick"]), int(event["robot"]), str(event["event"])
        except (KeyError, TypeError, ValueError):
            raise RunFileError(f"{path}: goal_events[{k}] lacks tick/robot/event") from None
        if kind == "assigned" and 0 <= robot < n and event.get("cell") is not None:
            goals[max(0, tick):, robot] = event["cell"]  # in force from the state of its tick
        elif kind == "reached":
            reached_at.append(tick)
    reached = None
    if "goal_events" in record:
        reached_at = np.sort(np.asarray(reached_at, dtype=np.int64))
        reached = np.searchsorted(reached_at, np.arange(frames), side="right").tolist()
    return RecordedRun(grid, list(range(frames)), positions, goals, reached,
                       int(record.get("episode", 0)), path.name)


def _describe(options: dict) -> str:
    if options.get("instance_file"):
        return options["instance_file"]
    if options.get("map_file"):
        return options["map_file"] + (f" + {options['scen_file']}" if options.get("scen_file") else "")
    return (f"--size {options.get('size')} --density {options.get('density')} "
            f"--seed {options.get('seed')}")


# ---- the rosbag2 --------------------------------------------------------------------------------
def load_bag(path, namespace: str = "", episode: int | None = None) -> RecordedRun:
    """The fleet's map and states from a rosbag2 (directory, or its .mcap file)."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2.errors import ReaderError
    from rosbags.typesys import Stores, get_typestore

    from mapf_fleet.fleet import topics as names

    from mapf_fleet.view import bag_salvage

    path = Path(path)
    bag_dir = path.parent if path.suffix == ".mcap" else path
    topics = {name: names.in_namespace(name, namespace) for name in (
        names.MAP_TOPIC, names.STATE_TOPIC, names.PROGRESS_TOPIC, names.OUTCOME_TOPIC)}
    maps, states, progress, outcomes, notes = [], {}, {}, set(), []

    def take(topic, stamp, msg):
        if topic == topics[names.MAP_TOPIC]:
            maps.append((stamp, msg))
        elif topic == topics[names.STATE_TOPIC]:
            states.setdefault(int(msg.episode), {})[int(msg.tick)] = (stamp, msg)
        elif topic == topics[names.PROGRESS_TOPIC]:
            progress.setdefault(int(msg.episode), {})[int(msg.tick)] = int(msg.goals_reached)
        elif topic == topics[names.OUTCOME_TOPIC]:
            outcomes.add(int(msg.episode))

    unfinished = bag_dir.is_dir() and not (bag_dir / "metadata.yaml").exists()
    try:
        if unfinished:  # the recorder was killed: its complete chunks (one per tick)
            mcap = path if path.suffix == ".mcap" else bag_salvage.mcap_file(bag_dir)
            if mcap is None:
                raise RunFileError(f"{path}: no metadata.yaml and no .mcap file: not a rosbag2")
            for topic, stamp, msg in bag_salvage.decoded_messages(mcap):
                if topic in topics.values():
                    take(topic, stamp, msg)
            notes.append(f"{path}: the bag was not closed (no metadata.yaml: its recorder was "
                         f"killed); read up to its last complete tick")
        else:
            with AnyReader([bag_dir],
                           default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
                wanted = [c for c in reader.connections if c.topic in topics.values()]
                # none wanted (another namespace): read nothing (no connections means all)
                for connection, stamp, raw in (reader.messages(connections=wanted) if wanted
                                               else ()):
                    take(connection.topic, stamp, reader.deserialize(raw, connection.msgtype))
    except bag_salvage.SalvageError as exc:
        raise RunFileError(str(exc)) from None
    except (ReaderError, FileNotFoundError, OSError) as exc:
        raise RunFileError(f"{path}: not a readable rosbag2 ({exc})") from None
    if not states:
        raise RunFileError(f"{path}: no {topics[names.STATE_TOPIC]} messages (a bag of "
                           f"`mapf-fleet record`{' --namespace ' + namespace if namespace else ''}?)")
    if not maps:
        raise RunFileError(f"{path}: no {topics[names.MAP_TOPIC]} message")
    if episode is None:  # the run of the last state recorded
        episode = max(states, key=lambda e: max(stamp for stamp, _ in states[e].values()))
    elif episode not in states:
        raise RunFileError(f"{path}: no states of episode {episode} (episodes: "
                           f"{', '.join(map(str, sorted(states)))})")
    by_tick = states[episode]
    ticks = sorted(by_tick)
    first_stamp = by_tick[ticks[0]][0]
    # the map published for this run: the last one before its first state (latched maps are
    # recorded when the recorder subscribes), else the first one
    before = [m for m in maps if m[0] <= first_stamp]
    grid, _ = names.occupancy_to_grid((before[-1] if before else maps[0])[1])
    positions = np.array([np.stack([by_tick[t][1].rows, by_tick[t][1].cols], 1) for t in ticks],
                         dtype=np.int64)
    goals = np.array([np.stack([by_tick[t][1].goal_rows, by_tick[t][1].goal_cols], 1)
                      for t in ticks], dtype=np.int64)
    reached = None
    if episode in progress:  # progress of tick k is published after the moves into k
        counts, last = [], 0
        for t in ticks:
            last = progress[episode].get(t, last)
            counts.append(last)
        reached = counts
    if episode not in outcomes:
        notes.append(f"{path}: the bag ends at tick {ticks[-1]} without the run's outcome "
                     f"({topics[names.OUTCOME_TOPIC]}): the fleet or its recorder was stopped "
                     f"before the run ended; rendering the ticks recorded")
    return RecordedRun(grid, ticks, positions, goals, reached, episode, bag_dir.name, notes)


def load_run(path, instance_options: dict, namespace: str = "",
             episode: int | None = None) -> RecordedRun:
    path = Path(path)
    if path.is_dir() or path.suffix == ".mcap":
        return load_bag(path, namespace, episode)
    return load_record(path, instance_options)


# ---- frames -------------------------------------------------------------------------------------
def captions(run: RecordedRun) -> list[str]:
    """Per frame: robots on goal, goals reached and throughput, as the live view counts them."""
    from mapf_fleet.view.picture import FleetPicture

    picture = FleetPicture()
    out = []
    n = run.positions.shape[1]
    for k, tick in enumerate(run.ticks):
        picture.set_state(run.episode, tick, run.positions[k], run.goals[k])
        if run.reached is not None:
            picture.set_progress(episode=run.episode, tick=tick, goals_reached=run.reached[k])
        snap = picture.snapshot()
        out.append(f"on goal {snap['on_goal']}/{n}  reached {snap['reached']}  "
                   f"{snap['throughput']:.2f}/tick")
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mapf-fleet render", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", required=True, metavar="RUN",
                   help="the run: JSON record (`up --record`) or rosbag2 directory / .mcap")
    p.add_argument("--out", required=True, help="output .gif / .webp / .mp4, or a folder for PNG frames")
    p.add_argument("--fps", type=float, default=8.0, help="frames per second (default %(default)s)")
    p.add_argument("--namespace", default="", help="a bag's fleet namespace (`up --namespace`)")
    p.add_argument("--episode", type=int, default=None, help="a bag's run (default: the last)")
    p.add_argument("--no-paths", action="store_true", help="do not draw the paths taken")
    group = p.add_argument_group("the instance of a JSON record without a map (as given to `up`)")
    group.add_argument("--instance", default="", help="instance YAML")
    group.add_argument("--map", default="", help="map file (MovingAI .map or Nav2 YAML)")
    group.add_argument("--scen", default="", help="MovingAI .scen (with --map)")
    group.add_argument("--cell-size", type=float, default=0.0, metavar="M",
                       help="a Nav2 --map: metres per grid cell, as given to `up` (default: one "
                            "pixel per cell)")
    group.add_argument("--size", type=int, default=16, help="generated map side (default 16)")
    group.add_argument("--density", type=float, default=0.3, help="default 0.3")
    group.add_argument("--seed", type=int, default=0, help="default 0")
    return p


def render_run(argv: list[str]) -> int:
    from mapf_fleet.evaluation.render import check_out, draw_frames, save_frames

    args = build_parser().parse_args(argv)
    if not args.fps > 0:  # also rejects nan
        print(f"mapf-fleet render: --fps must be > 0, got {args.fps:g}", file=sys.stderr)
        return 2
    options = {"instance_file": args.instance, "map_file": args.map, "scen_file": args.scen,
               "size": args.size, "density": args.density, "seed": args.seed,
               "cell_size": args.cell_size}
    try:
        check_out(args.out)
        run = load_run(args.run, options, args.namespace, args.episode)
    except (RunFileError, ValueError) as exc:
        print(f"mapf-fleet render: {exc}", file=sys.stderr)
        return 2
    for note in run.notes:
        print(f"mapf-fleet render: {note}", file=sys.stderr, flush=True)
    frames = draw_frames(run.grid, run.goals, run.positions, np.zeros((0, run.positions.shape[1]), bool),
                         f"{run.label} ticks {run.ticks[0]}-{run.ticks[-1]}",
                         trails=not args.no_paths, captions=captions(run))
    out = save_frames(args.out, frames, args.fps)
    print(f"{out}: {len(run.ticks)} frames (ticks {run.ticks[0]}-{run.ticks[-1]}) of "
          f"{run.positions.shape[1]} robots on a {run.grid.shape[0]}x{run.grid.shape[1]} map")
    return 0


def main(argv: list[str] | None = None) -> int:
    """`mapf-fleet render`: a recorded run with --run, else one episode of a policy
    (`evaluation.render`)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a == "--run" or a.startswith("--run=") for a in argv):
        return render_run(argv)
    from mapf_fleet.evaluation.render import main as render_episode

    return render_episode(argv)
