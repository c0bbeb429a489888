"""`mapf-fleet up`: start a simulated fleet (simulator + one policy node per robot), show live
progress, print the outcome and exit 0 on success.

Process layout: by default each policy node runs in its own process; `--nodes-per-process K`
hosts K robots' nodes per process (needed past ~32 processes, DESIGN.md section 2);
`--single-process` runs the simulator and every policy node in this process. The policy nodes of
one process share one hub (one subscription per shared topic, batched inference). With
`--real-robots` the aggregator replaces the simulator: the robots publish their own poses on
/robot_<i>/pose and follow /robot_<i>/waypoint. Every process gets
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST.

The simulator (or the aggregator) arbitrates each tick with `--conflict-rule`: `pibt_anchor`
(default: PIBT over the robots' ranked actions with the top-priority robot on its distance order;
nothing is reverted), `pibt` (CS-PIBT as published) or `revert` (the paper's environment: conflicting
first choices are reverted).

With no arguments: 8 simulated robots on a generated 16x16 map, checkpoint models/default.pt.
"""

from __future__ import annotations

import argparse
import contextlib
import glob
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from mapf_fleet.paths import data_root
from mapf_fleet.ros import common
from mapf_fleet.fleet.arbiter import CONFLICT_RULES, DEFAULT_CONFLICT_RULE
from mapf_fleet.ros.instances import InstanceSource

# where models/ lives: the install's share/mapf_fleet, else the checkout
DATA_ROOT = data_root("models")


DEFAULT_CHECKPOINT = DATA_ROOT / "models" / "default.pt"

# Robots' nodes one process hosts at most (`--single-process`: all of them; else
# `--nodes-per-process`). Creating the nodes of one process takes time that grows with the
# square of their number (every new publisher is matched against the process's others on the
# shared topics): 200 robots ~1 s, 500 ~10 s, 2000 ~3 min on a 2-core machine, 10000 would take
# about an hour before the first tick.
MAX_NODES_PER_PROCESS = 512
# ROS processes of one fleet on one domain that Fast DDS discovery on loopback was measured to
# handle (../shared/DESIGN.md, "Scale limits": about 32 are discovered; with 64 half never see
# each other and the shared-memory transport can deadlock). Above it `up` warns, not refuses.
MAX_DISCOVERED_PROCESSES = 32


def default_checkpoint() -> str:
    """models/default.pt if present, else the first DHC (or any) checkpoint in models/."""
    if DEFAULT_CHECKPOINT.is_file():
        return str(DEFAULT_CHECKPOINT)
    found = sorted(glob.glob(str(DATA_ROOT / "models" / "*.pt")))
    preferred = [f for f in found if "dhc" in Path(f).name.lower()] or found
    return preferred[0] if preferred else ""


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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mapf-fleet up", description=__doc__,
                                     formatter_class=_HelpFormatter)
    parser.add_argument("--checkpoint", default=None,
                        help="policy checkpoint (default: models/default.pt, else the first DHC "
                             "checkpoint in models/)")
    parser.add_argument("--num-robots", type=int, default=None,
                        help="robots of a generated instance, or the first N entries of --scen "
                             "(default: 8 generated, every entry of --scen)")
    parser.add_argument("--size", type=int, default=16, help="side of a generated map")
    parser.add_argument("--density", type=float, default=0.3,
                        help="obstacle density of a generated map, in [0, 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of a generated instance")
    parser.add_argument("--instance", default="", help="instance YAML (grid, starts, goals)")
    parser.add_argument("--map", default="",
                        help="the map: a MovingAI .map (with --scen for starts and goals), or a "
                             "building's Nav2 map_server YAML (image, resolution, origin, ...; "
                             "see --cell-size); without --scen, starts and goals are drawn from "
                             "--seed")
    parser.add_argument("--cell-size", type=float, default=None, metavar="M",
                        help="Nav2 map YAML: metres per grid cell, a whole number of image "
                             "pixels (default: one pixel per cell); a cell is blocked when any "
                             "of its pixels is occupied or unknown")
    parser.add_argument("--task-source", nargs="+", default=["instance"],
                        metavar="SOURCE [FILE]",
                        help="where goals come from: instance (the one-shot episode: every "
                             "robot to its goal, then the run ends), lifelong (a new random goal "
                             "on arrival, POGEMA's lifelong MAPF), tasks FILE (a YAML list of "
                             "goals or pickup/dropoff pairs for the nearest idle robot), "
                             "external (robots idle until goals come over ROS: goal_pose, "
                             "navigate_to_pose, mapf-fleet goal); goals given at run time work "
                             "with every source")
    parser.add_argument("--goal-seed", type=int, default=None,
                        help="seed of the lifelong goal stream (default: --seed)")
    parser.add_argument("--scen", default="", help="MovingAI .scen (with --map)")
    parser.add_argument("--max-steps", type=int, default=None,
                        help="tick limit (>= 1): a one-shot run fails when the robots are not "
                             "all on goal by then; a continuous one ends there (default: 256; "
                             "with --task-source external: none, 0, the run goes on until "
                             "Ctrl-C)")
    parser.add_argument("--decision-timeout", type=float, default=10.0,
                        help="seconds the simulator waits for a robot's move; a missing one is "
                             "stay, reported (> 0)")
    parser.add_argument("--comm-timeout", type=float, default=5.0,
                        help="seconds a robot waits for a peer's message before leaving it out "
                             "(> 0)")
    parser.add_argument("--startup-timeout", type=float, default=120.0,
                        help="seconds to wait for every robot to report ready before tick 0 "
                             "(> 0)")
    parser.add_argument("--conflict-rule", choices=CONFLICT_RULES, default=DEFAULT_CONFLICT_RULE,
                        help="how the arbiter resolves a tick: pibt (PIBT over the robots' "
                             "ranked actions), pibt_anchor (the same, the top-priority robot on "
                             "its distance order), lacam (a kept LaCAM plan over the robots' "
                             "rankings) or revert (the paper's rules on first choices)")
    parser.add_argument("--planning-budget", type=float, default=None,
                        help="--conflict-rule lacam: seconds of planning per re-plan "
                             "(default 1; > 0)")
    parser.add_argument("--preference-mode", default=None,
                        help="how policy nodes rank their actions from Q-values (default: "
                             "the policy nodes' preference_mode if a params file sets it, else "
                             "the ranking the checkpoint records for the conflict rule "
                             "(metadata rankings, e.g. a DAgger round's), else the rule's, "
                             "coordination.preferences.default_q_mode: confidence under "
                             "pibt_anchor, q under pibt and revert)")
    parser.add_argument("--nodes-per-process", type=int, default=1,
                        help="robots' policy nodes hosted per process (one hub each; 32 for "
                             "large fleets)")
    parser.add_argument("--single-process", action="store_true",
                        help="simulator and all policy nodes in this process")
    parser.add_argument("--real-robots", action="store_true",
                        help="real-robot mode: the aggregator (robots' own /robot_<i>/pose "
                        "feeds) instead of the simulator")
    parser.add_argument("--arrival-timeout", type=float, default=10.0,
                        help="real-robot mode: seconds for robots to reach their waypoints "
                             "(> 0)")
    parser.add_argument("--resolution", type=float, default=None,
                        help="metres per cell of the map and the poses (default: 1.0, or the "
                             "nodes' resolution parameter)")
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
    parser.add_argument("--params-file", default="", help="ROS parameters YAML for all nodes")
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
                     "task_source": "task_source", "goal_seed": "goal_seed",
                     "cell_size": "cell_size", "planning_budget": "planning_budget"}
POLICY_OPTION_PARAMS = {"checkpoint": "checkpoint", "comm_timeout": "comm_timeout",
                        "preference_mode": "preference_mode"}


def apply_parameter_sources(own: list[str], args, ros_args: list[str]) -> None:
    """Precedence as `ros2 launch` users expect: command line > params file > `up`'s defaults.
    Sets each option of `args` to the value its node will really get (the params file
    `--params-file F`, then `up`'s options given on the command line, then the user's
    `--ros-args` rules and files, in that order; see mapf_fleet.ros.params), and records what
    `_ros_args` needs: `args.ros_args`, `args.explicit_params`, `args.fixed_params`."""
    from mapf_fleet.ros import params as rp

    explicit_parser = build_parser()
    for action in explicit_parser._actions:
        action.default = argparse.SUPPRESS
    explicit = set(vars(explicit_parser.parse_args(own)))
    types = {action.dest: action.type for action in explicit_parser._actions if action.type}
    rules, ros_files, ros_namespace = rp.ros_arg_rules(ros_args)
    files = ([args.params_file] if args.params_file else [])
    for path in files + ros_files:
        rp.read_params_file(path)  # a missing or malformed file: one line, exit 2
    namespace = ros_namespace or getattr(args, "namespace", "") or "/"
    sim_name = "mapf_aggregator" if args.real_robots else "mapf_simulator"
    args.ros_args = list(ros_args)
    args.explicit_params = {param for table in (SIM_OPTION_PARAMS, POLICY_OPTION_PARAMS)
                            for option, param in table.items() if option in explicit}
    args.fixed_params = {}
    args.node_values = {}  # kind -> {parameter: value} from the params files, options and -p
    for kind, table, names in (("sim", SIM_OPTION_PARAMS, [sim_name]),
                               ("policy", POLICY_OPTION_PARAMS,
                                [f"mapf_policy_{i}" for i in range(1024)])):
        fixed: set[str] = set()
        for name in names:
            fqn = rp.node_fqn(name, namespace)
            fixed |= set(rp.params_file_values(files + ros_files, fqn))
            fixed |= set(rp.command_line_values(rules, name))
        args.fixed_params[kind] = fixed
        # the value the first node of this kind gets, in command-line order
        fqn = rp.node_fqn(names[0], namespace)
        values = rp.params_file_values(files, fqn)
        values.update({table[o]: getattr(args, o) for o in table if o in explicit})
        for index, arg in enumerate(ros_args[:-1]):
            if arg == "--params-file":
                values.update(rp.params_file_values([ros_args[index + 1]], fqn))
            elif arg in ("-p", "--param"):
                values.update(rp.command_line_values(rp.ros_arg_rules(
                    ["-p", ros_args[index + 1]])[0], names[0]))
        args.node_values[kind] = values
        for option, param in table.items():
            if param in values:
                value = values[param]
                try:
                    value = types[option](value) if option in types else value
                except (TypeError, ValueError):
                    raise ValueError(f"parameter {param}: expected {types[option].__name__}, "
                                     f"got {value!r}") from None
                setattr(args, option, value)
    args.fixed_params["both"] = args.fixed_params["sim"] | args.fixed_params["policy"]


# What a node refuses at start-up (or, for the simulator's runtime parameters, at its first
# tick), checked by `up` before anything starts: (node kind, parameter, check, condition)
VALUE_CHECKS = [
    ("sim", "max_steps", lambda v: v >= 0, ">= 1 (0: no limit, continuous task sources)"),
    ("sim", "cell_size", lambda v: v >= 0, "> 0"),
    ("sim", "decision_timeout", lambda v: v > 0, "> 0"),
    ("sim", "startup_timeout", lambda v: v > 0, "> 0"),
    ("sim", "arrival_timeout", lambda v: v > 0, "> 0"),
    ("sim", "resolution", lambda v: v > 0, "> 0"),
    ("sim", "tick_period", lambda v: v >= 0, ">= 0"),
    ("sim", "progress_every", lambda v: v >= 1, ">= 1"),
    ("sim", "start_tick", lambda v: v >= 0, ">= 0"),
    ("sim", "state_subscribers", lambda v: v >= 0, ">= 0"),
    ("policy", "comm_timeout", lambda v: v > 0, "> 0"),
    ("policy", "service_timeout", lambda v: v > 0, "> 0"),
    ("policy", "status_period", lambda v: v > 0, "> 0"),
    ("policy", "episode_timeout", lambda v: v > 0, "> 0"),
]
MAX_DOMAIN_ID = 232  # the largest ROS_DOMAIN_ID whose Fast DDS ports are valid


def value_problem(args) -> str:
    """The first value a node of this fleet would refuse ("" when none), as one line naming the
    option (or the parameter and where it came from) and the value: every value is checked
    before anything starts (issue 23, defect 5)."""
    options = {param: option for table in (SIM_OPTION_PARAMS, POLICY_OPTION_PARAMS)
               for option, param in table.items()}
    for kind, param, check, condition in VALUE_CHECKS:
        values = dict(getattr(args, "node_values", {}).get(kind, {}))
        table = SIM_OPTION_PARAMS if kind == "sim" else POLICY_OPTION_PARAMS
        values.update({p: getattr(args, o) for o, p in table.items()
                       if getattr(args, o, None) is not None})
        if param not in values:
            continue
        value = values[param]
        option = options.get(param)
        name = (f"--{option.replace('_', '-')}" if option and param in args.explicit_params
                else f"parameter {param}" + ("" if option else " (params file or -p)"))
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"{name} must be a number {condition}, got {value!r}"
        if not check(value):
            return f"{name} must be {condition}, got {value!r}"
    source = getattr(args, "task_source", "instance")
    if args.max_steps == 0 and source == "instance":
        name = "--max-steps" if "max_steps" in args.explicit_params else "parameter max_steps"
        return (f"{name} must be >= 1 with --task-source instance (0, no limit, is for the "
                f"continuous sources lifelong, tasks, external), got 0")
    if args.domain_id is not None and not 0 <= args.domain_id <= MAX_DOMAIN_ID:
        return f"--domain-id must be in 0-{MAX_DOMAIN_ID}, got {args.domain_id}"
    if args.nodes_per_process < 1:
        return f"--nodes-per-process must be >= 1, got {args.nodes_per_process}"
    if args.origin is not None and not args.real_robots:
        return ("--origin applies to --real-robots (the simulator's map has its corner at "
                "0, 0)")
    return ""


def default_robot_count(args) -> int:
    """--num-robots when not given: every entry of --scen, else 8 (a generated instance)."""
    if args.map and args.scen and not args.instance:
        from mapf_fleet.grid.movingai import read_scen

        return len(read_scen(args.scen))
    return 8


def _ros_args(params: dict, args, kind: str) -> list[str]:
    """A node's ROS arguments: the params file, `up`'s defaults that no params file or `-p`
    rule sets for it, the options given on `up`'s command line, the user's `--ros-args`
    (rcl: a later value replaces an earlier one)."""
    out = ["--ros-args"]
    if getattr(args, "namespace", ""):
        out += ["-r", f"__ns:=/{args.namespace.strip('/')}"]
    if args.params_file:
        out += ["--params-file", args.params_file]
    fixed = args.fixed_params.get(kind, set())
    for name, value in params.items():
        if name in args.explicit_params or name not in fixed:
            out += ["-p", f"{name}:={value}"]
    return out + list(args.ros_args)


def task_source_problem(args) -> str:
    """Split `--task-source SOURCE [FILE]` into args.task_source / args.task_file; the problem
    ("" when none)."""
    from mapf_fleet.fleet.tasks import TASK_SOURCES

    source, rest = args.task_source[0], args.task_source[1:]
    args.task_source, args.task_file = source, rest[0] if rest else ""
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


def main(argv: list[str] | None = None) -> int:
    from mapf_fleet.ros.processes import stop_signals

    signals = stop_signals()  # first thing: SIGINT / SIGTERM while loading are kept, no traceback
    argv = list(sys.argv[1:] if argv is None else argv)
    own, ros_args = common.split_ros_args(argv)
    parser = build_parser()
    args = parser.parse_args(own)
    problem = task_source_problem(args)
    if problem:
        print(f"mapf-fleet up: {problem}", file=sys.stderr)
        return 2
    apply_parameter_sources(own, args, ros_args)
    if args.max_steps is None:  # external goals come when they come: no tick limit
        args.max_steps = 0 if args.task_source == "external" else 256
    problem = value_problem(args)
    if problem:  # before anything starts (a node would refuse it, some only after seconds)
        print(f"mapf-fleet up: {problem}", file=sys.stderr)
        return 2
    checkpoint = args.checkpoint or default_checkpoint()
    if not checkpoint or not Path(checkpoint).is_file():
        if args.checkpoint:
            problem = f"checkpoint not found: {args.checkpoint!r}"
        else:
            problem = f"no checkpoint in {DATA_ROOT / 'models'} (default {DEFAULT_CHECKPOINT.name})"
        print(f"mapf-fleet up: {problem}. Pass --checkpoint FILE.pt (a file written by "
              f"mapf_fleet.models.save_checkpoint, e.g. by training), or put one at "
              f"{DEFAULT_CHECKPOINT}.", file=sys.stderr)
        return 2
    if args.real_robots and args.single_process:
        print("mapf-fleet up: --real-robots runs the aggregator in its own process; drop "
              "--single-process", file=sys.stderr)
        return 2
    if args.preference_mode is not None:
        from mapf_fleet.coordination.preferences import PREFERENCE_MODES

        if args.preference_mode not in PREFERENCE_MODES:
            print(f"mapf-fleet up: --preference-mode must be one of "
                  f"{', '.join(PREFERENCE_MODES)}", file=sys.stderr)
            return 2
    problem = checkpoint_problem(checkpoint)
    if problem:  # before anything starts: the policy processes would die one by one
        print(f"mapf-fleet up: {problem}", file=sys.stderr)
        return 2
    try:
        if args.num_robots is None:
            args.num_robots = default_robot_count(args)
        source = InstanceSource(args.instance, args.map, args.scen, args.num_robots, args.size,
                                args.density, args.seed, args.cell_size or 0.0)
        num_robots = source.load().num_agents
    except (ValueError, OSError) as exc:
        print(f"mapf-fleet up: bad instance: {exc}", file=sys.stderr)
        return 2
    if args.task_file:  # a bad task file: one line naming file, task and field, before anything
        from mapf_fleet.fleet.tasks import TaskFileError, load_task_file

        geometry = common.MapGeometry(*(source.geometry() or (
            args.resolution or 1.0, *(args.origin or (0.0, 0.0)))))
        try:
            load_task_file(args.task_file, num_robots=num_robots, cell_of=geometry.xy_to_cell)
        except TaskFileError as exc:
            print(f"mapf-fleet up: {exc}", file=sys.stderr)
            return 2
    problem = layout_problem(num_robots, args.single_process, args.nodes_per_process)
    if problem:
        print(f"mapf-fleet up: {problem}", file=sys.stderr)
        return 2
    warning = layout_warning(num_robots, args.single_process, args.nodes_per_process,
                             recorder=bool(args.bag))
    if warning:
        print(f"mapf-fleet up: {warning}", file=sys.stderr)
    if args.bag and Path(args.bag).exists():
        print(f"mapf-fleet up: --bag {args.bag} exists already: a rosbag2 is written into a new "
              f"directory", file=sys.stderr)
        return 2
    env = common.prepare_environment(dict(os.environ))
    if args.domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(args.domain_id)
    # the default record and the policy processes' logs (in --log-dir when given); removed when
    # `up` ends after a successful run, kept after a failed one
    work = tempfile.mkdtemp(prefix="mapf_fleet_")
    args.work_dir = args.log_dir or work
    if args.log_dir:
        try:
            os.makedirs(args.log_dir, exist_ok=True)
        except OSError as exc:
            print(f"mapf-fleet up: --log-dir {args.log_dir}: {exc.strerror or exc}",
                  file=sys.stderr)
            return 2
    record = args.record or os.path.join(work, "run.json")
    sim_params, policy_params = node_parameters(args, checkpoint, record, num_robots)
    started = time.monotonic()
    result = 1
    try:
        if args.single_process:
            os.environ.update(env)
            code, problem = run_single_process(num_robots, sim_params, policy_params, args)
        else:
            code, problem = run_processes(num_robots, sim_params, policy_params, args, env)
        elapsed = time.monotonic() - started
        result = finish(code, problem, record, elapsed, bool(args.record))
        return result
    finally:
        # a run stopped by the user (Ctrl-C, SIGTERM: 130 / 143) did not fail: nothing to keep
        keep_logs(work, args.log_dir, failed=result not in (0, 130, 143))
        signals.restore()


def keep_logs(work: str, log_dir: str, failed: bool) -> None:
    """The temporary work directory goes, unless the run failed and the policy processes' logs
    are in it (no --log-dir): then its path is printed, so a user can see why a hub stalled."""
    logs = sorted(glob.glob(os.path.join(work, "*.log")))
    if failed and logs and not log_dir:
        print(f"mapf-fleet up: the policy processes' logs are kept in {work}", file=sys.stderr)
        return
    if log_dir and glob.glob(os.path.join(log_dir, "*.log")):
        print(f"mapf-fleet up: the policy processes' logs are in {log_dir}", file=sys.stderr)
    shutil.rmtree(work, ignore_errors=True)


def node_parameters(args, checkpoint: str, record: str, num_robots: int) -> tuple[dict, dict]:
    """The parameters `up` gives the simulator (or aggregator) and the policy nodes, from its
    options (`_ros_args` leaves out those a params file or -p rule sets, unless the option was
    given)."""
    sim_params = {"instance_file": args.instance, "map_file": args.map, "scen_file": args.scen,
                  "num_robots": args.num_robots, "size": args.size, "density": args.density,
                  "seed": args.seed, "max_steps": args.max_steps,
                  "task_source": args.task_source, "task_file": args.task_file,
                  "decision_timeout": args.decision_timeout,
                  "startup_timeout": args.startup_timeout, "record_file": record,
                  "conflict_rule": args.conflict_rule}
    sim_params = {k: v for k, v in sim_params.items() if v != ""}
    if args.resolution is not None:
        sim_params["resolution"] = args.resolution
    for option in ("goal_seed", "cell_size", "planning_budget"):
        if getattr(args, option) is not None:
            sim_params[option] = getattr(args, option)
    if args.real_robots:
        sim_params = {k: v for k, v in sim_params.items() if k in _aggregator_parameters()}
        sim_params["arrival_timeout"] = args.arrival_timeout
        if args.origin is not None:
            sim_params["origin_x"], sim_params["origin_y"] = args.origin
    if args.bag:  # tick 0 waits until the hubs and the recorder hear the state: no tick missed
        sim_params["state_subscribers"] = (
            policy_processes(num_robots, args.single_process, args.nodes_per_process) + 1)
    # the policy nodes' default preference_mode follows the checkpoint and the arbiter's rule (a
    # params file's or the command line's preference_mode still wins: up passes none unless
    # --preference-mode)
    policy_params = {"checkpoint": checkpoint, "comm_timeout": args.comm_timeout,
                     "conflict_rule": args.conflict_rule}
    if args.preference_mode is not None:
        policy_params["preference_mode"] = args.preference_mode
    return sim_params, policy_params


def checkpoint_problem(path: str) -> str:
    """"" when `path` loads as a policy (as the policy nodes load it), else the reason, e.g.
    "bad.pt: not a readable checkpoint (corrupt, truncated or not weights-only): ..."."""
    from mapf_fleet.models.checkpoint import load_checkpoint

    try:
        load_checkpoint(path)
    except (ValueError, OSError) as exc:  # CheckpointError is a ValueError
        return str(exc).strip().splitlines()[0] if str(exc).strip() else repr(exc)
    return ""


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


def layout_warning(num_robots: int, single_process: bool, nodes_per_process: int,
                   recorder: bool = False) -> str:
    """A warning ("" when none) when the layout needs more ROS processes (the simulator or
    aggregator, one per group of robots' nodes, the recorder) than MAX_DISCOVERED_PROCESSES."""
    processes = 1 + policy_processes(num_robots, single_process, nodes_per_process) + int(recorder)
    if processes <= MAX_DISCOVERED_PROCESSES:
        return ""
    suggest = -(-num_robots // max(1, MAX_DISCOVERED_PROCESSES - 1 - int(recorder)))
    return (f"warning: this layout starts {processes} ROS processes on one domain; Fast DDS "
            f"discovery on loopback was measured reliable up to about "
            f"{MAX_DISCOVERED_PROCESSES} (above it processes may never see each other and robots "
            f"miss decisions). Use --nodes-per-process {suggest} or more.")


def finish(code: int, problem: str, record: str, elapsed: float, keep_record: bool) -> int:
    """`up`'s exit code after its run: the outcome's (0 success, 1 failure), 128 + the signal
    that stopped it (130 / 143, the outcome "stopped at tick k" still reported), 1 when a
    process of the fleet died (`problem`), or the simulator's own error code (2: it refused its
    parameters, with its message above)."""
    if code not in (0, 1) and code < 128 and not problem:
        return code
    if code >= 128 and not Path(record).exists():
        print(f"mapf-fleet up: stopped by signal {code - 128} before the run started",
              file=sys.stderr)
        return code
    result = report(record, elapsed, keep_record)
    if code >= 128:
        return code
    return 1 if problem else result


def _aggregator_parameters() -> set[str]:
    from mapf_fleet.ros.aggregator_node import PARAMETERS

    return set(PARAMETERS)


def run_processes(num_robots, sim_params, policy_params, args, env) -> tuple[int, str]:
    """Start the policy processes and the simulator (or aggregator) and supervise them
    (`processes.supervise`): the simulator's output is shown (unless --quiet), each policy
    process's goes to a log in `args.work_dir`, reported (its last lines) if it dies; SIGINT /
    SIGTERM stop the run (record, "stopped at tick k") and every child. Each child runs in its
    own session (a terminal's Ctrl-C reaches `up` only, which passes it on once) and gets
    SIGTERM if `up` dies. With --bag the recorder runs beside them (`bag_recording`). (exit
    code: the simulator's, or 128 + the signal; the problem reported, or "")."""
    from mapf_fleet.ros.processes import Child, stop_children, stop_signals, supervise

    runner = [sys.executable, "-m", "mapf_fleet.ros.run"]
    signals = stop_signals()
    if signals.requested:
        return signals.exit_code, ""
    with bag_recording(args, env, signals) as recorder:
        if recorder is False:
            return (signals.exit_code or 2), ""
        children: list[Child] = []
        try:
            k = args.nodes_per_process
            for first in range(0, num_robots, k):
                ids = f"{first}-{min(first + k, num_robots) - 1}"
                children.append(Child(
                    f"policy process (robots {ids})",
                    runner + ["policy", "--robots", ids] + _ros_args(policy_params, args, "policy"),
                    env, log_path=os.path.join(args.work_dir, f"policy_{ids}.log")))
            name = "aggregator" if args.real_robots else "simulator"
            echo = None if args.quiet else (lambda line: print(line, flush=True))
            main = Child(name, runner + [name] + _ros_args(sim_params, args, "sim"), env,
                         echo=echo)
        except BaseException:
            stop_children(children)
            raise
        code, problem = supervise(main, children, signals, echoed=not args.quiet,
                                  watched=[recorder] if recorder else [])
    if signals.requested:
        return signals.exit_code, problem
    return (1 if problem else code), problem


@contextlib.contextmanager
def bag_recording(args, env, signals, ready_timeout: float = 120.0):
    """With `--bag DIR`: the rosbag2 recorder (`mapf_fleet.ros.bag`, `mapf-fleet record DIR` in
    the fleet's namespace) as a child process, started before the fleet and ready (its
    subscriptions exist) before the fleet starts, so nothing is missed; stopped after the fleet
    with `bag.stop_recorder` (the last messages in flight, then SIGINT: the bag is closed).
    Yields the recorder's `processes.Child`, None without --bag, False when it could not start
    (its output is shown)."""
    if not getattr(args, "bag", ""):
        yield None
        return
    import threading

    from mapf_fleet.ros import params as rp
    from mapf_fleet.ros.bag import READY_PREFIX, recorder_command, stop_recorder
    from mapf_fleet.ros.processes import Child

    namespace = rp.ros_arg_rules(list(getattr(args, "ros_args", [])))[2] or args.namespace
    ready = threading.Event()

    def echo(line: str) -> None:
        if line.startswith(READY_PREFIX):
            ready.set()
        elif not args.quiet or line.startswith("mapf-fleet record:"):
            print(line, flush=True)

    recorder = Child("bag recorder", recorder_command(args.bag, namespace=namespace or ""), env,
                     echo=echo)
    deadline = time.monotonic() + ready_timeout
    while not ready.wait(0.1):
        if recorder.poll() is not None or signals.requested or time.monotonic() > deadline:
            if recorder.poll() is None:
                stop_recorder(recorder.proc, grace=0.0)
            if not signals.requested:
                print(f"mapf-fleet up: {recorder.report()}", file=sys.stderr)
            yield False
            return
    try:
        yield recorder
    finally:
        code = stop_recorder(recorder.proc)
        recorder.wait_output()
        if code != 0:
            print(f"mapf-fleet up: {recorder.report()}", file=sys.stderr)


def run_single_process(num_robots, sim_params, policy_params, args) -> tuple[int, str]:
    """The simulator and every policy node in this process (with --bag, the recorder beside it
    as a child process). (exit code, problem) as `run_processes`."""
    from mapf_fleet.ros.processes import stop_signals

    signals = stop_signals()
    with bag_recording(args, dict(os.environ), signals) as recorder:
        if recorder is False:
            return (signals.exit_code or 2), ""
        return _run_in_this_process(num_robots, sim_params, policy_params, args)


def _run_in_this_process(num_robots, sim_params, policy_params, args) -> tuple[int, str]:
    import rclpy

    from mapf_fleet.ros.common import init_process
    from mapf_fleet.ros.policy_node import PolicyNode, host_kwargs, spin_policy_nodes
    from mapf_fleet.ros.simulator_node import SimulatorNode

    # the same ROS arguments (and precedence) as the processes get, for every node of this one
    # SIGINT / SIGTERM stop the simulator's run (record, "stopped at tick k"): exit 130 / 143
    signals = init_process(["up"] + _ros_args({**sim_params, **policy_params}, args, "both"))
    try:
        simulator = SimulatorNode()
        options = host_kwargs(num_robots)
        first = PolicyNode(robot_id=0, checkpoint=policy_params["checkpoint"], **options)
        policies = [first] + [PolicyNode(robot_id=i, model=first.model,
                                         metadata=first.checkpoint_metadata, **options)
                              for i in range(1, num_robots)]
        # one hub drives every robot of this process; the simulator shares the executor
        code = spin_policy_nodes(policies, until=simulator.finished.is_set,
                                 extra_nodes=[simulator], side_nodes=simulator.extra_nodes,
                                 on_started=simulator.start,
                                 signals=signals, on_stop=simulator.ticker.stop)
        if code:
            return code, ("" if signals.requested else "a callback failed (logged above)")
        return (0 if simulator.outcome is not None and simulator.outcome.success else 1), ""
    finally:
        rclpy.try_shutdown()
        signals.restore()


def report(record_path: str, elapsed: float, show_path: bool = True) -> int:
    """Print the run's outcome and its speed; 0 on success, else 1. The ticks/s are measured
    from the first tick (the record's `run_seconds`), not over start-up."""
    try:
        record = json.loads(Path(record_path).read_text())
    except (OSError, ValueError) as exc:
        print(f"mapf-fleet up: no outcome ({exc})", file=sys.stderr)
        return 1
    ticks = int(record.get("steps", 0))
    run_seconds = float(record.get("run_seconds", 0.0))
    print(f"outcome: {record['summary']}")
    speed = (f"{ticks} ticks in {run_seconds:.1f} s from the first tick, "
             f"{ticks / run_seconds:.2f} ticks/s" if ticks and run_seconds > 0 else "no tick")
    print(f"wall time {elapsed:.1f} s; {speed}"
          + (f"; record: {record_path}" if show_path else ""))
    return 0 if record.get("success") else 1
