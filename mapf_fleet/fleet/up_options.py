"""`mapf-fleet up`'s options and its nodes' parameters, ROS-free: the parser (`build_parser`),
every node's parameters resolved from the tables of `fleet.parameters` (`plan_parameters`,
`plan_policy_parameters`: defaults < params file < options < `--ros-args -p`) and the checks
that refuse a value before anything starts (one line each, `UpError`). `ros.launcher.prepare`
adds what needs the ROS side or the networks (the checkpoint loads, the bag recorder) and
starts the processes."""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from mapf_fleet.coordination.pibt import CONFLICT_RULES
from mapf_fleet.fleet import parameters as P

# the user's help text of `mapf-fleet up`
DESCRIPTION = """`mapf-fleet up`: start a simulated fleet (simulator + one policy node per robot), show live
progress, print the outcome and exit 0 on success.

Process layout: by default each policy node runs in its own process; `--nodes-per-process K`
hosts K robots' nodes per process (needed past ~32 processes: Fast DDS discovery on loopback;
from 256 robots at most 8 processes, K = ceil(robots / 8), e.g. 64 for 512: the layouts measured
to get ready, `up` warns otherwise);
`--single-process` runs the simulator and every policy node in this process. The policy nodes of
one process share one hub (one subscription per shared topic, batched inference). With
`--real-robots` the aggregator replaces the simulator: the robots publish their own poses on
/robot_<i>/pose and follow /robot_<i>/waypoint. Every process gets
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST.

The simulator (or the aggregator) arbitrates each tick with `--conflict-rule`: `pibt_anchor_swap`
(default: PIBT over the robots' ranked actions with the top-priority robot on its distance order
and lacam3's swap in corridors; nothing is reverted), `pibt_anchor` (the same without swap),
`pibt` (CS-PIBT as published), the other `_swap` / `_hindrance` variants, `lacam` (a kept LaCAM
plan over the robots' rankings, repaired when something leaves it, `--planning-budget` seconds per
tick, else the `pibt_anchor_swap` step) or `revert` (the paper's environment: conflicting first choices
are reverted).

With no arguments: 8 simulated robots on a generated 16x16 map, checkpoint models/default.pt.
"""

# Robots' nodes one process hosts at most (`--single-process`: all of them; else
# `--nodes-per-process`). Creating the nodes of one process takes time that grows with the
# square of their number (every new publisher is matched against the process's others on the
# shared topics): 200 robots ~1 s, 500 ~10 s, 2000 ~3 min on a 2-core machine, 10000 would take
# about an hour before the first tick.
MAX_NODES_PER_PROCESS = 512
# ROS processes of one fleet on one domain that Fast DDS discovery on loopback was measured to
# handle (docs/fleet.md, Process layouts: about 32 are discovered; with 64 half never see
# each other and the shared-memory transport can deadlock). Above it `up` warns, not refuses.
MAX_DISCOVERED_PROCESSES = 32
# A fleet of LARGE_FLEET_ROBOTS robots or more in at most LARGE_FLEET_PROCESSES policy processes:
# the layouts measured to get ready at that size (docs/fleet.md, Process layouts: 256 robots as
# 8 x 32, 512 as 8 x 64; 512 as 16 x 32 never did). Every process discovers the per-robot
# endpoints of every other, so discovery grows with processes times robots, and every process
# starts its nodes on its own on a machine that runs them all.
LARGE_FLEET_ROBOTS = 256
LARGE_FLEET_PROCESSES = 8


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """The module docstring as written, and every option's default after its help text (unless
    the text already says its default, or there is none to state)."""

    def _get_help_string(self, action):
        text = action.help or ""
        default = action.default
        if ("default" in text or default is None or default is False or default == ""
                or default is argparse.SUPPRESS or not action.option_strings):
            return text
        return f"{text} (default: %(default)s)"


def _default(table_name: str) -> str:
    """' (default: X)' of a parameter, from the nodes' table (one truth)."""
    return f" (default: {P.SIMULATOR.get(table_name, P.POLICY.get(table_name)).default})"


def build_parser() -> argparse.ArgumentParser:
    """`up`'s options. Those that set a node parameter default to None (not given: the
    parameter's value comes from its table, a params file or -p); their help states the table's
    default."""
    sim = P.SIMULATOR
    parser = argparse.ArgumentParser(prog="mapf-fleet up", description=DESCRIPTION,
                                     formatter_class=_HelpFormatter)
    parser.add_argument("--checkpoint", default=None,
                        help="policy checkpoint (default: models/default.pt, else the first DHC "
                             "checkpoint in models/)")
    parser.add_argument("--num-robots", type=int, default=None,
                        help="robots of a generated instance, or the first N entries of --scen "
                             "(default: 8 generated, every entry of --scen)")
    parser.add_argument("--size", type=int, default=None,
                        help="side of a generated map" + _default("size"))
    parser.add_argument("--density", type=float, default=None,
                        help="obstacle density of a generated map, in [0, 1)"
                             + _default("density"))
    parser.add_argument("--seed", type=int, default=None,
                        help="seed of a generated instance" + _default("seed"))
    parser.add_argument("--instance", default=None,
                        help="instance YAML (grid, starts, goals)")
    parser.add_argument("--map", default=None,
                        help="the map: a MovingAI .map (with --scen for starts and goals), or a "
                             "building's Nav2 map_server YAML (image, resolution, origin, ...; "
                             "see --cell-size); without --scen, starts and goals are drawn from "
                             "--seed")
    parser.add_argument("--cell-size", type=float, default=None, metavar="M",
                        help="Nav2 map YAML: metres per grid cell, a whole number of image "
                             "pixels (default: one pixel per cell); a cell is blocked when any "
                             "of its pixels is occupied or unknown (as the YAML's thresholds "
                             "read them: under Nav2's free_thresh 0.25 map_saver's unknown grey "
                             "205 reads as free, and up warns); with --map F.yaml only")
    parser.add_argument("--task-source", nargs="+", default=None,
                        metavar="SOURCE [FILE]",
                        help="where goals come from: instance (the one-shot episode: every "
                             "robot to its goal, then the run ends), lifelong (a new random goal "
                             "on arrival, POGEMA's lifelong MAPF), tasks FILE (a YAML list of "
                             "goals or pickup/dropoff pairs for the nearest idle robot), "
                             "external (robots idle until goals come over ROS: goal_pose, "
                             "navigate_to_pose, mapf-fleet goal); goals given at run time work "
                             "with every source (default: instance)")
    parser.add_argument("--goal-seed", type=int, default=None,
                        help="seed of the lifelong goal stream (default: --seed)")
    parser.add_argument("--scen", default=None, help="MovingAI .scen (with --map)")
    parser.add_argument("--max-steps", type=int, default=None,
                        help="tick limit (>= 1): a one-shot run fails when the robots are not "
                             f"all on goal by then; a continuous one ends there (default: "
                             f"{sim['max_steps'].default}; with --task-source external: none, "
                             f"0, the run goes on until Ctrl-C)")
    parser.add_argument("--decision-timeout", type=float, default=None,
                        help="seconds the simulator waits for a robot's move; a missing one is "
                             "stay, reported (> 0)" + _default("decision_timeout"))
    parser.add_argument("--comm-timeout", type=float, default=None,
                        help="seconds a robot waits for a peer's message before leaving it out "
                             "(> 0)" + _default("comm_timeout"))
    parser.add_argument("--startup-timeout", type=float, default=None,
                        help="seconds to wait for every robot to report ready before tick 0 "
                             "(> 0)" + _default("startup_timeout"))
    parser.add_argument("--conflict-rule", choices=CONFLICT_RULES, default=None,
                        help="how the arbiter resolves a tick: pibt (PIBT over the robots' "
                             "ranked actions), pibt_anchor (the same, the top-priority robot on "
                             "its distance order), their _swap / _hindrance variants "
                             "(docs/coordination.md), lacam (a kept LaCAM plan over the robots' "
                             "rankings) or revert (the paper's rules on first choices)"
                             + _default("conflict_rule"))
    parser.add_argument("--planning-budget", type=float, default=None,
                        help="--conflict-rule lacam: seconds of planning per re-plan (> 0)"
                             + _default("planning_budget"))
    parser.add_argument("--ranking", choices=P.RANKINGS, default=None,
                        help="how policy nodes rank their actions from Q-values (default: "
                             "the policy nodes' ranking if a params file sets it, else "
                             "the ranking the checkpoint records for the conflict rule "
                             "(metadata rankings, e.g. a DAgger round's), else the rule's, "
                             "coordination.ranking.default_ranking: confidence under "
                             "pibt_anchor, q under pibt and revert)")
    parser.add_argument("--preference-mode", dest="preference_mode", choices=P.RANKINGS,
                        default=None, help="deprecated spelling of --ranking")
    parser.add_argument("--nodes-per-process", type=int, default=1,
                        help="robots' policy nodes hosted per process (one hub each; 32 for "
                             "large fleets)")
    parser.add_argument("--single-process", action="store_true",
                        help="simulator and all policy nodes in this process")
    parser.add_argument("--real-robots", action="store_true",
                        help="real-robot mode: the aggregator (robots' own /robot_<i>/pose "
                        "feeds) instead of the simulator")
    parser.add_argument("--arrival-timeout", type=float, default=None,
                        help="real-robot mode: seconds for robots to reach their waypoints "
                             "(> 0)" + f" (default: {P.AGGREGATOR['arrival_timeout'].default})")
    parser.add_argument("--resolution", type=float, default=None,
                        help="metres per cell of the map and the poses, not with a Nav2 map "
                             "(it has its own)" + _default("resolution"))
    parser.add_argument("--origin", type=float, nargs=2, default=None, metavar=("X", "Y"),
                        help="real-robot mode: x, y (metres) of the map's corner, where cell "
                             "(0, 0) starts (default: 0 0)")
    parser.add_argument("--record", default="", help="write trajectory and outcome JSON here")
    parser.add_argument("--bag", default="", metavar="DIR",
                        help="also record the fleet's topics into the new rosbag2 DIR (MCAP; "
                             "`mapf-fleet record DIR` started beside the fleet, closed at the "
                             "end)")
    parser.add_argument("--log-dir", default="", metavar="DIR",
                        help="keep the policy processes' logs in DIR (created if needed; "
                             "default: a temporary directory, removed after a successful run "
                             "and kept, with its path printed, after a failed one)")
    parser.add_argument("--domain-id", type=int, default=None,
                        help="ROS_DOMAIN_ID to use, 0-232 (default: the environment's)")
    parser.add_argument("--params-file", default="",
                        help="ROS parameters YAML for the nodes (config/fleet/fleet.yaml shows "
                             "every parameter); the options above and --ros-args -p win over it")
    parser.add_argument("--namespace", default="",
                        help="ROS namespace of the whole fleet (e.g. /fleet_a: topics "
                             "/fleet_a/fleet/state, /fleet_a/robot_0/pose, ...), so fleets in "
                             "different namespaces share a ROS_DOMAIN_ID; same as --ros-args "
                             "-r __ns:=/fleet_a")
    parser.add_argument("--quiet", action="store_true", help="no live progress")
    return parser


# `up` options -> the parameters they set, of the simulator (or aggregator) and of the policy nodes
SIM_OPTION_PARAMS = {"instance": "instance_file", "map": "map_file", "scen": "scen_file",
                     "num_robots": "num_robots", "size": "size", "density": "density",
                     "seed": "seed", "max_steps": "max_steps",
                     "decision_timeout": "decision_timeout", "startup_timeout": "startup_timeout",
                     "conflict_rule": "conflict_rule", "arrival_timeout": "arrival_timeout",
                     "record": "record_file", "resolution": "resolution",
                     "task_source": "task_source", "task_file": "task_file",
                     "goal_seed": "goal_seed", "cell_size": "cell_size",
                     "planning_budget": "planning_budget"}
POLICY_OPTION_PARAMS = {"checkpoint": "checkpoint", "comm_timeout": "comm_timeout",
                        "ranking": "ranking"}
MAX_DOMAIN_ID = 232  # the largest ROS_DOMAIN_ID whose Fast DDS ports are valid
# a ROS namespace: tokens of letters, digits and _, none starting with a digit
NAMESPACE_RE = re.compile(r"/?([A-Za-z_][A-Za-z0-9_]*)(/[A-Za-z_][A-Za-z0-9_]*)*/?")


class UpError(ValueError):
    """A value `up` refuses before anything starts: one line, exit 2."""


def _is_up_option(arg: str) -> bool:
    option = arg.split("=", 1)[0]
    return option.startswith("--") and any(
        option in a.option_strings for a in build_parser()._actions)


def _option_name(dest: str) -> str:
    return "--" + dest.replace("_", "-")


@dataclass
class Plan:
    """What `up` starts, every value checked: the nodes' resolved parameters ({node name:
    {name: value}}), where each came from, the fleet's namespace and the ROS arguments passed
    on as they are."""
    sim_name: str
    values: dict
    origin: dict
    namespace: str
    passed: list
    warnings: list = field(default_factory=list)
    params_path: str = ""

    @property
    def sim(self) -> dict:
        return self.values[self.sim_name]

    @property
    def policy(self) -> dict:
        return self.values.get("mapf_policy_0", {})

    def ros_args(self) -> list[str]:
        """A node's ROS arguments: the fleet's namespace and the merged params file."""
        out = ["--ros-args"]
        if self.namespace.strip("/"):
            out += ["-r", f"__ns:=/{self.namespace.strip('/')}"]
        if self.params_path:
            out += ["--params-file", self.params_path]
        return out + list(self.passed)


def explicit_options(args) -> dict:
    """{node kind: {parameter: (value, option)}} of the options given on the command line."""
    out = {"sim": {}, "policy": {}}
    for kind, table in (("sim", SIM_OPTION_PARAMS), ("policy", POLICY_OPTION_PARAMS)):
        for option, param in table.items():
            value = getattr(args, option, None)
            if value is not None and value != "":
                out[kind][param] = (value, _option_name(option).replace("--task-file",
                                                                        "--task-source tasks"))
    if args.origin is not None:
        out["sim"]["origin_x"] = (args.origin[0], "--origin")
        out["sim"]["origin_y"] = (args.origin[1], "--origin")
    return out


def plan_parameters(args, ros_argv: list[str]) -> Plan:
    """Every node's parameters, resolved (defaults < params file < options < --ros-args) and
    checked; UpError with one line for anything refused. Sets `args`' options to the values
    the nodes will get."""
    if args.preference_mode is not None:
        print("mapf-fleet up: --preference-mode is deprecated, use --ranking", file=sys.stderr)
        if args.ranking is None:
            args.ranking = args.preference_mode
    problem = task_source_problem(args)
    if problem:
        raise UpError(problem)
    try:
        ros = P.read_ros_args(ros_argv, _is_up_option)
    except ValueError as exc:
        raise UpError(str(exc)) from None
    if args.namespace and ros.namespace and args.namespace.strip("/") != ros.namespace.strip("/"):
        raise UpError(f"--namespace {args.namespace} and --ros-args -r __ns:={ros.namespace} "
                      f"disagree")
    namespace = ros.namespace or args.namespace
    if namespace and not NAMESPACE_RE.fullmatch(namespace):
        raise UpError(f"--namespace must be a ROS namespace (tokens of letters, digits and _, "
                      f"none starting with a digit, separated by /), got {namespace!r}")
    if args.domain_id is not None and not 0 <= args.domain_id <= MAX_DOMAIN_ID:
        raise UpError(f"--domain-id must be in 0-{MAX_DOMAIN_ID}, got {args.domain_id}")
    if args.nodes_per_process < 1:
        raise UpError(f"--nodes-per-process must be >= 1, got {args.nodes_per_process}")
    not_applying = options_not_applying(args)
    if not_applying:
        raise UpError(not_applying)
    sim_name = "mapf_aggregator" if args.real_robots else "mapf_simulator"
    user_files = [args.params_file] if args.params_file else []
    options = explicit_options(args)
    try:
        values, origin, warnings = P.merged_values([sim_name], namespace, user_files, options,
                                                   ros)
    except FileNotFoundError as exc:
        raise UpError(str(exc)) from None
    except ValueError as exc:
        raise UpError(str(exc)) from None
    sim = values[sim_name]
    if origin[sim_name]["max_steps"] == "default" and sim["task_source"] == "external":
        sim["max_steps"] = 0  # external goals come when they come: no tick limit
    if sim["max_steps"] == 0 and sim["task_source"] == "instance":
        where = origin[sim_name]["max_steps"]
        raise UpError(f"{where}: max_steps must be >= 1 with task_source instance (0, no limit, "
                      f"is for the continuous sources lifelong, tasks, external), got 0"
                      .replace("--max-steps: max_steps", "--max-steps"))
    if args.goal_seed is not None and sim["task_source"] != "lifelong":
        raise UpError("--goal-seed applies to --task-source lifelong")
    if sim["task_source"] == "tasks" and not sim["task_file"]:
        raise UpError("task_source tasks needs a task file: --task-source tasks FILE")
    for option, param in SIM_OPTION_PARAMS.items():
        if param in sim:
            setattr(args, option, sim[param])
    args.task_source = sim["task_source"]
    args.namespace = namespace
    return Plan(sim_name, values, origin, namespace, ros.passed, warnings)


def plan_policy_parameters(plan: Plan, args, ros_argv: list[str], num_robots: int,
                           checkpoint: str) -> None:
    """The policy nodes' resolved parameters into `plan` (their conflict rule follows the
    simulator's unless set for them; the checkpoint defaults to `checkpoint`)."""
    ros = P.read_ros_args(ros_argv, _is_up_option)
    names = [f"mapf_policy_{i}" for i in range(num_robots)]
    user_files = [args.params_file] if args.params_file else []
    defaults = {"policy": {"conflict_rule": plan.sim["conflict_rule"],
                           "checkpoint": checkpoint}}
    options = explicit_options(args)
    try:
        values, origin, warnings = P.merged_values([plan.sim_name] + names, plan.namespace,
                                                   user_files, options, ros, defaults)
    except ValueError as exc:
        raise UpError(str(exc)) from None
    for name in names:
        plan.values[name] = values[name]
        plan.origin[name] = origin[name]
    plan.warnings += [w for w in warnings if w not in plan.warnings]
    if num_robots >= LARGE_FLEET_ROBOTS and plan.origin[plan.sim_name].get(
            "robot_actions") == "default":
        # 512 per-robot action servers (4,096 endpoints) took a fleet from ready in 55 s and
        # 1.96 ticks/s to 129 s and 0.87 (docs/results.md): large fleets leave them out
        plan.sim["robot_actions"] = False
        plan.warnings.append(
            f"note: {num_robots} robots: no per-robot robot_<i>/navigate_to_pose action servers "
            f"(goals: fleet/navigate_to_pose with the robot in the goal, `mapf-fleet goal`, "
            f"robot_<i>/goal_pose, fleet/submit_tasks); -p robot_actions:=true serves them")


def options_not_applying(args) -> str:
    """The first option given that the run would not use ("" when none)."""
    nav2 = bool(args.map) and str(args.map).lower().endswith((".yaml", ".yml"))
    rules = [
        (args.origin is not None and not args.real_robots,
         "--origin applies to --real-robots (the simulator's map has its corner at 0, 0)"),
        (args.arrival_timeout is not None and not args.real_robots,
         "--arrival-timeout applies to --real-robots"),
        (args.cell_size is not None and not nav2,
         "--cell-size applies to a Nav2 map (--map F.yaml)"),
        (args.resolution is not None and nav2,
         "--resolution does not apply to a Nav2 map: its YAML gives the resolution (use "
         "--cell-size for metres per grid cell)"),
        (args.origin is not None and nav2,
         "--origin does not apply to a Nav2 map: its YAML gives the origin"),
        (args.num_robots is not None and bool(args.instance),
         "--num-robots does not apply to --instance: the instance file gives the robots"),
        (bool(args.scen) and not args.map, "--scen needs --map (the .map it was made for)"),
        (bool(args.instance) and bool(args.map), "--instance and --map: give one of them"),
        (any(getattr(args, o) is not None for o in ("size", "density"))
         and bool(args.instance or args.map),
         "--size and --density apply to a generated map, not to --instance or --map"),
    ]
    for refused, text in rules:
        if refused:
            return text
    return ""


def record_problem(path: str, option: str = "--record") -> str:
    """Why the run's record cannot be written at `path` ("" when it can): checked by creating
    and removing a file beside it, so a directory, a missing or read-only folder or /proc is
    refused before anything starts."""
    target = Path(path)
    if target.is_dir():
        return f"{option} {path}: is a directory"
    parent = target.parent
    if not parent.is_dir():
        return f"{option} {path}: folder {parent} does not exist"
    if target.exists() and not os.access(target, os.W_OK):
        return f"{option} {path}: not writable"
    try:
        with tempfile.NamedTemporaryFile(dir=parent, prefix=f".{target.name}.", delete=True):
            pass
    except OSError as exc:
        return f"{option} {path}: cannot write in {parent} ({exc.strerror or exc})"
    return ""


def default_robot_count(args) -> int:
    """--num-robots when not given: every entry of --scen, else 8 (a generated instance)."""
    if args.map and args.scen and not args.instance:
        from mapf_fleet.grid.movingai import read_scen

        return len(read_scen(args.scen))
    return P.SIMULATOR["num_robots"].default


def task_source_problem(args) -> str:
    """Split `--task-source SOURCE [FILE]` into args.task_source / args.task_file; the problem
    ("" when none)."""
    from mapf_fleet.fleet.tasks import TASK_SOURCES

    if args.task_source is None:
        args.task_file = None
        return ""
    source, rest = args.task_source[0], args.task_source[1:]
    args.task_source, args.task_file = source, rest[0] if rest else None
    if source not in TASK_SOURCES:
        return f"--task-source must be one of {', '.join(TASK_SOURCES)}, got {source!r}"
    if source == "tasks":
        if len(rest) != 1:
            return "--task-source tasks needs exactly one task file: --task-source tasks FILE"
        if not Path(rest[0]).is_file():
            return f"--task-source tasks: task file not found: {rest[0]}"
    elif rest:
        return f"--task-source {source} takes no file (got {' '.join(rest)})"
    return ""


def unknown_as_free_warning(map_file: str) -> str:
    """A warning ("" when none) for a Nav2 map whose thresholds read map_saver's unknown grey
    as free (its cells do not block)."""
    if not str(map_file).lower().endswith((".yaml", ".yml")):
        return ""
    from mapf_fleet.grid.nav2_map import read_nav2_yaml, saver_unknown_read_as_free

    meta = read_nav2_yaml(map_file)
    count = saver_unknown_read_as_free(meta)
    if not count:
        return ""
    return (f"warning: {map_file}: {count} pixels of grey 205 (map_saver's unknown) read as "
            f"free under free_thresh {meta.free_thresh:g}, as Nav2's map_server reads them; "
            f"set free_thresh: 0.196 in {map_file} to have them block")


def policy_value(args, ros_argv, name):
    """The value a params file or -p gives the first policy node's `name` ("" when none)."""
    ros = P.read_ros_args(ros_argv, _is_up_option)
    files = [args.params_file] if args.params_file else []
    try:
        values, origin, _ = P.merged_values(["mapf_simulator", "mapf_policy_0"], args.namespace,
                                            files, {}, ros)
    except ValueError as exc:
        raise UpError(str(exc)) from None
    return values["mapf_policy_0"][name] if origin["mapf_policy_0"][name] != "default" else ""


def layout_problem(num_robots: int, single_process: bool, nodes_per_process: int) -> str:
    """Why this process layout is refused ("" when it is not): more than
    MAX_NODES_PER_PROCESS robots' nodes in one process."""
    per_process = num_robots if single_process else min(nodes_per_process, num_robots)
    if per_process <= MAX_NODES_PER_PROCESS:
        return ""
    layout = "--single-process" if single_process else f"--nodes-per-process {nodes_per_process}"
    return (f"{layout} would host {per_process} robots' nodes in one process; the limit is "
            f"{MAX_NODES_PER_PROCESS}, because creating them takes time growing with the square "
            f"of their number (500 ~10 s, 2000 ~3 min, 10000 about an hour before the first "
            f"tick). Use --nodes-per-process K with K <= {MAX_NODES_PER_PROCESS} (e.g. 8).")


def policy_processes(num_robots: int, single_process: bool, nodes_per_process: int) -> int:
    """Processes hosting the robots' policy nodes (hubs): one with --single-process."""
    return 1 if single_process else -(-num_robots // max(1, nodes_per_process))


def recommended_nodes_per_process(num_robots: int, recorder: bool = False) -> int:
    """The `--nodes-per-process` `up` recommends for `num_robots`: a large fleet (at least
    LARGE_FLEET_ROBOTS) in LARGE_FLEET_PROCESSES processes (at most MAX_NODES_PER_PROCESS nodes
    each); a smaller one in as few as keep every ROS process within MAX_DISCOVERED_PROCESSES
    (1: a process per robot)."""
    if num_robots >= LARGE_FLEET_ROBOTS:
        return min(-(-num_robots // LARGE_FLEET_PROCESSES), MAX_NODES_PER_PROCESS)
    return max(1, -(-num_robots // max(1, MAX_DISCOVERED_PROCESSES - 1 - int(recorder))))


def layout_warning(num_robots: int, single_process: bool, nodes_per_process: int,
                   recorder: bool = False) -> str:
    """A warning ("" when none) when the layout has more policy processes than a large fleet
    was measured to get ready with (LARGE_FLEET_PROCESSES from LARGE_FLEET_ROBOTS robots), or
    needs more ROS processes (the simulator or aggregator, one per group of robots' nodes, the
    recorder) than MAX_DISCOVERED_PROCESSES."""
    hubs = policy_processes(num_robots, single_process, nodes_per_process)
    if num_robots >= LARGE_FLEET_ROBOTS and hubs > LARGE_FLEET_PROCESSES:
        suggest = recommended_nodes_per_process(num_robots, recorder)
        if nodes_per_process < suggest:
            return (f"warning: {num_robots} robots in {hubs} policy processes; fleets of "
                    f"{LARGE_FLEET_ROBOTS}+ robots were measured to get ready only in "
                    f"{LARGE_FLEET_PROCESSES} or fewer (512 robots: 8 x 64 ready in 53 s, "
                    f"16 x 32 never), since DDS discovery grows with processes times robots "
                    f"and each process starts its nodes on its own. Use --nodes-per-process "
                    f"{suggest} ({policy_processes(num_robots, False, suggest)} processes).")
    processes = 1 + hubs + int(recorder)
    if processes <= MAX_DISCOVERED_PROCESSES:
        return ""
    suggest = recommended_nodes_per_process(num_robots, recorder)
    return (f"warning: this layout starts {processes} ROS processes on one domain; Fast DDS "
            f"discovery on loopback was measured reliable up to about "
            f"{MAX_DISCOVERED_PROCESSES} (above it processes may never see each other and robots "
            f"miss decisions). Use --nodes-per-process {suggest} or more.")
