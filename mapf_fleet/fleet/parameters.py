"""The ROS parameters of the fleet's nodes, one table per node kind (plain Python, no rclpy).

Each parameter has its name, type (its default's), default, description, check, whether it
may change during a run and, when `mapf-fleet up` offers it, its `up` option (`Option`: flag,
help, when it applies). The nodes declare and check their parameters from these tables
(`fleet_io.declare_parameters`, `policy_node.PolicyNode`), `mapf-fleet up` builds its options
from them (`up_options.build_parser`) and writes one merged parameters file from them
(`merged_values`), docs/fleet.md's parameter list is generated from them
(`fleet.parameter_doc`), and config/fleet/fleet.yaml is tested against them. Adding a
parameter to the fleet is one entry here plus the code that reads it.

`up` resolves every node's values itself, in one order: the table's defaults < the user's
params file(s) < `up`'s options < `-p` rules, and hands the nodes one params file with a fully
resolved entry per node (`write_params_file`), so what a node runs with is what `up` checked.
A user's params file is read by its node keys' last token (`/**`, `*`, `mapf_simulator`,
`mapf_policy_*`, `mapf_policy_3`: fnmatch against the node name); a key naming another
namespace than the fleet's applies to no node of it.
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass
from pathlib import Path

import yaml

from mapf_fleet.aliases import PARAMETERS as PARAMETER_ALIASES
from mapf_fleet.coordination.ranking import (DEFAULT_RANKING_BY_RULE, RANKINGS,
                                             default_ranking)
from mapf_fleet.coordination.rules import FLEET_GUIDANCE
from mapf_fleet.fleet.arbiter import CONFLICT_RULES, DEFAULT_CONFLICT_RULE
from mapf_fleet.fleet.param import (GENERATED_MAP, LIFELONG, NAV2_MAP, REAL_ROBOTS, Applies,
                                    Option, Param)
from mapf_fleet.fleet.ros_args import RosArgs, read_ros_args
from mapf_fleet.fleet.tasks import TASK_SOURCES

__all__ = ["AGGREGATOR", "ALIASES", "Applies", "NODE_TABLES", "Option", "POLICY", "Param",
           "RosArgs", "SIMULATOR", "merged_values", "read_params_file", "read_ros_args",
           "table_of", "write_params_file"]


def _positive(text: str = "seconds") -> dict:
    return {"check": lambda v: v > 0, "condition": "> 0"}


DEVICES = ("auto", "cpu", "cuda")


def resolve_guidance(value: str) -> str | None:
    """The guidance a node builds its world with (None: no guidance, "none"): "highways", a
    guidance file or a cost model (`grid.guidance_made.GuidanceSource`)."""
    return None if value in ("none", "") else str(value)


def _guidance_ok(value: str) -> bool:
    from mapf_fleet.grid.guidance_made import GuidanceSource

    try:
        GuidanceSource.parse(value)
        return True
    except ValueError:
        return False


# the simulator's, the aggregator's and the policy nodes' guidance: one value for the fleet,
# by default the fleet's (`coordination.rules.FLEET_GUIDANCE`, what `evaluate` measures)
GUIDANCE = Param(FLEET_GUIDANCE, "guidance graph read by every distance to a goal (the rule's "
                                 "order, the robots' heuristic channels): none (BFS steps), "
                                 "highways (hand-made crisscross lanes), a guidance file "
                                 "(*.guidance.npz), a cost model (*.costmodel.json), or online "
                                 "guidance updated from the robots' moves: congestion or an "
                                 "online model (*.online.json); every node of the fleet gets "
                                 "the same",
                 _guidance_ok, "none, highways, congestion, or an existing *.guidance.npz, "
                               "*.costmodel.json or *.online.json",
                 option=Option("--guidance", metavar="none|highways|congestion|FILE"))


# both lockstep nodes (simulator, aggregator) take their instance and their tick from these
_INSTANCE = {
    "instance_file": Param("", "instance YAML (grid rows, starts, goals); overrides the rest",
                           option=Option("--instance")),
    "map_file": Param("", "the map: a MovingAI .map (with scen_file for starts and goals) or a "
                          "Nav2 map_server YAML (see cell_size); without scen_file, starts and "
                          "goals are drawn from seed",
                      option=Option("--map", help="the map: a MovingAI .map (with --scen for "
                                    "starts and goals), or a building's Nav2 map_server YAML "
                                    "(image, resolution, origin, ...; see --cell-size); "
                                    "without --scen, starts and goals are drawn from --seed")),
    "scen_file": Param("", "MovingAI .scen file (with map_file)",
                       option=Option("--scen", help="MovingAI .scen (with --map)", applies=(
                           Applies(lambda f: bool(f.map),
                                   "needs --map (the .map it was made for)"),))),
    "num_robots": Param(8, "robots to generate or to take from the .scen file",
                        lambda v: v >= 1, ">= 1",
                        option=Option("--num-robots", help="robots of a generated instance, or "
                                      "the first N entries of --scen (default: 8 generated, "
                                      "every entry of --scen)", applies=(
                                          Applies(lambda f: not f.instance,
                                                  "does not apply to --instance: the instance "
                                                  "file gives the robots"),))),
    "size": Param(16, "side of a generated square map", lambda v: v >= 2, ">= 2",
                  option=Option("--size", applies=(GENERATED_MAP,))),
    "density": Param(0.3, "obstacle density of a generated map", lambda v: 0 <= v < 1,
                     "in [0, 1)", option=Option("--density", applies=(GENERATED_MAP,))),
    "seed": Param(0, "seed of a generated instance (and of the starts and goals drawn on a "
                     "map_file without scen_file)", lambda v: v >= 0, ">= 0",
                  option=Option("--seed", help="seed of a generated instance")),
    "cell_size": Param(0.0, "Nav2 map YAML (map_file F.yaml): metres per grid cell, a whole "
                            "number of image pixels (0: one pixel per cell); a cell is blocked "
                            "when any of its pixels is occupied or unknown",
                       lambda v: v >= 0, ">= 0 (0: one pixel per cell)",
                       option=Option("--cell-size", metavar="M", applies=(NAV2_MAP,), help=(
                           "Nav2 map YAML: metres per grid cell, a whole number of image "
                           "pixels (default: one pixel per cell); a cell is blocked when any of "
                           "its pixels is occupied or unknown (as the YAML's thresholds read "
                           "them: under Nav2's free_thresh 0.25 map_saver's unknown grey 205 "
                           "reads as free, and up warns); with --map F.yaml only"))),
}
_RUN = {
    "conflict_rule": Param(DEFAULT_CONFLICT_RULE,
                           "how the tick's decisions become moves: pibt (PIBT over the robots' "
                           "ranked actions, nothing reverted), pibt_anchor (the same, the "
                           "top-priority robot on its distance order), their _swap / _hindrance "
                           "variants (coordination.rules.COORDINATED_RULES), _epibt (3-move "
                           "operations) and _lns (a plan of the next ticks repaired every tick; "
                           "the default) rules, lacam (a kept LaCAM "
                           "plan over the robots' rankings, re-planned when something leaves it) "
                           "or revert (the paper's rules on the first choices)",
                           choices=CONFLICT_RULES, option=Option("--conflict-rule", help=(
                               "how the arbiter resolves a tick: pibt (PIBT over the robots' "
                               "ranked actions), pibt_anchor (the same, the top-priority robot "
                               "on its distance order), their _swap / _hindrance variants, the "
                               "_epibt and _lns rules (docs/coordination.md), lacam (a kept "
                               "LaCAM plan over the "
                               "robots' rankings) or revert (the paper's rules on first "
                               "choices)"))),
    "planning_budget": Param(1.0, "conflict_rule lacam: seconds of planning per re-plan; a tick "
                                  "without a plan in it takes pibt_anchor_swap's step",
                             **_positive(), option=Option("--planning-budget")),
    "max_steps": Param(256, "tick limit: a one-shot run fails when robots are not all on goal "
                            "by then; continuous runs end there (0: no limit, continuous task "
                            "sources)", lambda v: v >= 0,
                       ">= 1 (0: no limit, continuous task sources)",
                       option=Option("--max-steps", help=(
                           "tick limit (>= 1): a one-shot run fails when the robots are not all "
                           "on goal by then; a continuous one ends there (default: 256; with "
                           "--task-source external: none, 0, the run goes on until Ctrl-C)"))),
    "task_source": Param("instance", f"where goals come from: {' | '.join(TASK_SOURCES)} "
                                     f"(instance: the one-shot episode; lifelong: a new random "
                                     f"goal on arrival; tasks: task_file's goals / pick-up-drop-"
                                     f"off pairs for the nearest idle robot; external: only "
                                     f"goals given at run time)", choices=TASK_SOURCES,
                         option=Option("--task-source", nargs="+", metavar="SOURCE [FILE]",
                                       part=0, help=(
                             "where goals come from: instance (the one-shot episode: every "
                             "robot to its goal, then the run ends), lifelong (a new random goal "
                             "on arrival, POGEMA's lifelong MAPF), tasks FILE (a YAML list of "
                             "goals or pickup/dropoff pairs for the nearest idle robot), "
                             "external (robots idle until goals come over ROS: goal_pose, "
                             "navigate_to_pose, mapf-fleet goal); goals given at run time work "
                             "with every source (default: instance)"))),
    "task_file": Param("", "task list YAML for task_source tasks",
                       option=Option("--task-source", part=1)),
    "goal_seed": Param(-1, "seed of the lifelong goal stream (-1: the instance seed)",
                       lambda v: v >= -1, ">= -1 (-1: the instance seed)",
                       option=Option("--goal-seed", applies=(LIFELONG,), help=(
                           "seed of the lifelong goal stream (default: --seed)"))),
    "decision_timeout": Param(10.0, "seconds to wait for a robot's move before it counts as "
                                    "stay (reported)", **_positive(), runtime=True,
                              option=Option("--decision-timeout")),
    "startup_timeout": Param(120.0, "seconds to wait for every policy node to report ready",
                             **_positive(), option=Option("--startup-timeout")),
    "resolution": Param(1.0, "metres per cell in poses and the map", **_positive(),
                        option=Option("--resolution", applies=(Applies(
                            lambda f: not f.nav2_map, "does not apply to a Nav2 map: its YAML "
                            "gives the resolution (use --cell-size for metres per grid "
                            "cell)"),))),
    "record_file": Param("", "write the run's trajectory and outcome to this JSON file",
                         option=Option("--record", help="write trajectory and outcome JSON "
                                                        "here")),
    "progress_every": Param(10, "log progress every this many ticks", lambda v: v >= 1, ">= 1",
                            runtime=True),
    "state_subscribers": Param(0, "before tick 0, also wait (up to startup_timeout) until the "
                                  "fleet state has this many matched subscribers (`up --bag`: "
                                  "the policy processes and the recorder, so the bag misses no "
                                  "tick); 0: no wait", lambda v: v >= 0, ">= 0"),
    "robot_actions": Param(True, "serve Nav2's per-robot action robot_<i>/navigate_to_pose for "
                                 "every robot (fleet/navigate_to_pose, the robot in the goal, "
                                 "is always served); `up` leaves them out from 256 robots "
                                 "(docs/fleet.md, Large fleets)"),
    "state_recorder": Param("", "before tick 0, also wait (up to startup_timeout) until the "
                                "node of this name (`up --bag`: mapf_fleet_recorder) has a "
                                "subscription matched to the fleet state, so the bag has every "
                                "tick; empty: no wait"),
    "guidance": GUIDANCE,
}

SIMULATOR = {
    **_INSTANCE,
    **_RUN,
    "tick_period": Param(0.0, "minimum seconds per tick (0: as fast as the robots decide)",
                         lambda v: v >= 0, ">= 0", runtime=True),
    "start_tick": Param(0, "first tick number (a restarted simulator may continue a count)",
                        lambda v: v >= 0, ">= 0"),
}

AGGREGATOR = {
    **_INSTANCE,
    "instance_file": Param("", "instance YAML (grid rows, starts, goals): map and goals"),
    "scen_file": Param("", "MovingAI .scen file (with map_file): goals"),
    **_RUN,
    "startup_timeout": Param(120.0, "seconds to wait for every robot's pose and policy node",
                             **_positive()),
    "resolution": Param(1.0, "metres per cell (a Nav2 map_file sets its own)", **_positive()),
    "arrival_timeout": Param(10.0, "seconds to wait for robots to reach their waypoints",
                             **_positive(), runtime=True,
                             option=Option("--arrival-timeout", applies=(REAL_ROBOTS,))),
    "pose_timeout": Param(3.0, "seconds without a pose message after which a robot is reported "
                               "silent and held as an obstacle (the run ends when every robot "
                               "is)", **_positive()),
    "origin_x": Param(0.0, "x of the map's corner (cell (0, 0) starts there; a Nav2 map sets "
                           "its own)",
                      option=Option("--origin", nargs=2, metavar=("X", "Y"), part=0, applies=(
                          Applies(lambda f: f.real_robots, "applies to --real-robots (the "
                                  "simulator's map has its corner at 0, 0)"),
                          Applies(lambda f: not f.nav2_map, "does not apply to a Nav2 map: its "
                                  "YAML gives the origin")),
                          help="real-robot mode: x, y (metres) of the map's corner, where cell "
                               "(0, 0) starts (default: 0 0)")),
    "origin_y": Param(0.0, "y of the map's corner", option=Option("--origin", part=1)),
}

POLICY = {
    "robot_id": Param(0, "index of this robot in the fleet state", lambda v: v >= 0, ">= 0"),
    "checkpoint": Param("", "checkpoint file (mapf_fleet.models.save_checkpoint) to run",
                        option=Option("--checkpoint", help=(
                            "policy checkpoint (default: models/default.pt, else the first DHC "
                            "checkpoint in models/)"))),
    "device": Param("auto", "where the policy nodes run inference: auto (cuda when "
                            "torch.cuda.is_available(), else cpu), cpu or cuda",
                    choices=DEVICES, option=Option("--device")),
    "guidance": GUIDANCE,
    "comm_timeout": Param(5.0, "seconds to wait for a peer's message before leaving it out "
                               "(reported)", **_positive(), option=Option("--comm-timeout")),
    "service_timeout": Param(2.0, "seconds to wait for a peer's DCC service to be discovered",
                             **_positive()),
    "status_period": Param(0.5, "seconds between readiness heartbeats", **_positive()),
    "per_robot_messages": Param(False, "send each robot's move (RobotMove on /fleet/moves) and "
                                       "heartbeat (RobotStatus on /fleet/robot_status) as a "
                                       "message of its own instead of one RobotMoves "
                                       "(/fleet/move_batches) a tick and one HubStatus "
                                       "(/fleet/hub_status) a period for all the robots of "
                                       "the process"),
    "episode_timeout": Param(30.0, "seconds without a fleet state of the run this robot serves "
                                   "after which another simulator's run may take it over",
                             **_positive()),
    "conflict_rule": Param(DEFAULT_CONFLICT_RULE,
                           "the arbiter's conflict rule (the simulator's or aggregator's; `up` "
                           "passes its own): it sets the default ranking",
                           choices=CONFLICT_RULES),
    "ranking": Param("", "how a robot ranks its five actions from its Q-values for the arbiter: "
                         f"one of {', '.join(RANKINGS)}; empty: the ranking the checkpoint "
                         "records for the conflict rule (metadata rankings, e.g. a DAgger "
                         "round's), else the rule's default ("
                     + ", ".join(f"{m} under {r}" for r, m in DEFAULT_RANKING_BY_RULE.items())
                     + "; an _epibt or _lns rule its base rule's"
                     + f"; {default_ranking('revert')} otherwise)", choices=("",) + RANKINGS,
                     option=Option("--ranking", help=(
                         "how policy nodes rank their actions from Q-values (default: the "
                         "policy nodes' ranking if a params file sets it, else the ranking the "
                         "checkpoint records for the conflict rule (metadata rankings, e.g. a "
                         "DAgger round's), else the rule's, coordination.ranking."
                         "default_ranking: confidence under pibt_anchor, q under pibt and "
                         "revert)"))),
}

# deprecated parameter names still read (a warning each): old name -> name
ALIASES = PARAMETER_ALIASES
# parameters every rclpy node has: a params file may set them for any node
STANDARD = ("use_sim_time", "start_type_description_service")

NODE_TABLES = {"mapf_simulator": SIMULATOR, "mapf_aggregator": AGGREGATOR,
               "mapf_policy": POLICY}


def table_of(node_name: str) -> dict:
    """The table of node `node_name` (mapf_policy_3 -> POLICY)."""
    if node_name.startswith("mapf_policy"):
        return POLICY
    return NODE_TABLES[node_name]


def runtime_names(table: dict) -> list[str]:
    return [name for name, p in table.items() if p.runtime]


def parameter_problem(table: dict, name: str, value) -> str:
    """'decision_timeout must be > 0, got 0' ("" when fine) for a value a node would get."""
    if name in ALIASES and ALIASES[name] in table:
        name = ALIASES[name]
    if name not in table:
        return f"{name}: no such parameter"
    text = table[name].problem(value)
    return f"{name} {text}" if text else ""


def alias_warning(name: str) -> str:
    return (f"parameter {name} is deprecated, use {ALIASES[name]} (read as {ALIASES[name]} for "
            f"now)")


def check_values(table: dict, values: dict, where: str = "parameter") -> dict:
    """`values` coerced to the table's types; ValueError with one line ("parameter size must be
    >= 2, got 1") for the first refused one."""
    out = {}
    for name, value in values.items():
        problem = parameter_problem(table, name, value)
        if problem:
            raise ValueError(f"{where} {problem}")
        out[name] = table[ALIASES.get(name, name) if name not in table else name].coerce(value)
    return out


# ---- params files, `-p` rules ----

def _flatten(values: dict, prefix: str = "") -> dict:
    out = {}
    for name, value in values.items():
        full = f"{prefix}{name}"
        if isinstance(value, dict):
            out.update(_flatten(value, full + "."))
        else:
            out[full] = value
    return out


def read_params_file(path) -> list[tuple[str, dict]]:
    """[(node key, {parameter: value})] of a ROS 2 parameters YAML, in file order.
    FileNotFoundError / ValueError (naming the file) for a missing or malformed one."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"params file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not valid YAML ({exc})") from None
    except OSError as exc:
        raise ValueError(f"{path}: {exc.strerror or exc}") from None
    if data is None:
        return []
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected node names mapping to ros__parameters")
    entries: list[tuple[str, dict]] = []

    def walk(node: dict, prefix: str):
        for key, value in node.items():
            if key == "ros__parameters":
                if not isinstance(value, dict):
                    raise ValueError(f"{path}: {prefix or '/'}: ros__parameters must be a "
                                     f"mapping, found {value!r}")
                entries.append((prefix or "/**", _flatten(value)))
            elif isinstance(value, dict):
                walk(value, f"{prefix.rstrip('/')}/{str(key).strip('/')}")
            else:
                raise ValueError(f"{path}: {prefix}/{key}: expected a node name mapping to "
                                 f"ros__parameters, found {value!r}")

    walk(data, "")
    return entries


def key_applies(key: str, node_name: str, namespace: str = "") -> bool:
    """Whether params-file node key `key` names node `node_name` of a fleet in `namespace`: its
    last token matches the name (fnmatch; `**` every node) and the tokens before it are `**`
    or the namespace."""
    tokens = key.strip("/").split("/")
    name, before = tokens[-1], [t for t in tokens[:-1] if t != "**"]
    if name != "**" and not fnmatch.fnmatchcase(node_name, name):
        return False
    if "**" in tokens[:-1] or name == "**":
        return True
    return "/".join(before) == namespace.strip("/")


def _known_anywhere(name: str, tables) -> bool:
    return (name in STANDARD or name.startswith("qos_overrides.") or name in ALIASES
            or any(name in table for table in tables))


def merged_values(node_names: list[str], namespace: str, user_files: list[str],
                  options: dict, ros: RosArgs, defaults: dict | None = None):
    """Every node's parameter values as `up` hands them over: the table's defaults <
    `defaults` ({node kind: {name: value}}, `up`'s choices for this run) < the user's params
    files `user_files` < `options` ({node kind: {name: (value, option)}}, the options given) <
    the `--ros-args` sources in order. Node kind: 'sim' (the first name) or 'policy'.
    Returns ({node name: {name: value}}, {node name: {name: where it came from}}); ValueError
    with one line (file or option, field, value) for an unknown parameter or a refused value;
    a deprecated alias is read as its name (warnings: the third value returned)."""
    defaults = defaults or {}
    values, origin, warnings = {}, {}, []
    file_entries = {}
    for path in user_files + [s[1] for s in ros.sources if s[0] == "file"]:
        if path not in file_entries:
            file_entries[path] = read_params_file(path)

    def set_value(node, name, value, where):
        table = table_of(node)
        if name in ALIASES and ALIASES[name] in table:
            note = f"{where}: {alias_warning(name)}"
            if note not in warnings:
                warnings.append(note)
            name = ALIASES[name]
        if name not in table:
            return
        problem = table[name].problem(value)
        if problem:  # an option names its field itself ("--size must be >= 2, got 1")
            one = where.startswith("--") and where != "--origin"
            raise ValueError(f"{where} {problem}" if one else f"{where}: {name} {problem}")
        values[node][name] = table[name].coerce(value)
        origin[node][name] = where

    def apply_file(path, node):
        for key, params in file_entries[path]:
            if key_applies(key, node, namespace):
                for name, value in params.items():
                    set_value(node, name, value, f"params file {path}: {key}")

    kinds = [(node_names[0], table_of(node_names[0])), ("mapf_policy_0", POLICY)]
    tables = [t for _, t in kinds]

    def names_kind(key, node):
        last = key.strip("/").split("/")[-1]
        return key_applies(key, node, namespace) or (
            node == "mapf_policy_0" and last.startswith("mapf_policy"))

    # a section for the lockstep node of the other mode (one file serves both: the shipped
    # config/fleet/fleet.yaml) is checked against that node's table, not this run's
    other = [(n, t) for n, t in NODE_TABLES.items() if n != node_names[0] and t is not POLICY]
    for path, entries in file_entries.items():  # unknown keys: refused, whatever the node
        for key, params in entries:
            named = [t for n, t in kinds + other if names_kind(key, n)]
            for name in params:
                if not _known_anywhere(name, named or tables):
                    known = sorted(set().union(*(named or tables)))
                    raise ValueError(f"params file {path}: {key}: unknown parameter {name!r} "
                                     f"(known: {', '.join(known)})")
    for source in ros.sources:
        if source[0] == "rule":
            _, node, name, value, text = source
            if not _known_anywhere(name, tables):
                raise ValueError(f"-p {text}: unknown parameter {name!r}")
    for index, node in enumerate(node_names):
        kind = "sim" if index == 0 else "policy"
        table = table_of(node)
        values[node] = {name: p.default for name, p in table.items()}
        origin[node] = {name: "default" for name in table}
        for name, value in defaults.get(kind, {}).items():
            set_value(node, name, value, "default")
        for path in user_files:
            apply_file(path, node)
        for name, (value, option) in options.get(kind, {}).items():
            set_value(node, name, value, option)
        for source in ros.sources:
            if source[0] == "file":
                apply_file(source[1], node)
            else:
                _, target, name, value, text = source
                if not target or fnmatch.fnmatchcase(node, target.strip("/").split("/")[-1]):
                    set_value(node, name, value, f"-p {text}")
    return values, origin, warnings


def write_params_file(path, values: dict, namespace: str = "", skip=("robot_id",)) -> None:
    """One entry per node, keyed by its full name, every value resolved."""
    prefix = "/" + namespace.strip("/") if namespace.strip("/") else ""
    data = {f"{prefix}/{node}": {"ros__parameters": {k: v for k, v in params.items()
                                                 if k not in skip}}
            for node, params in values.items()}
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False))
