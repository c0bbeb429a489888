"""`mapf-fleet up`'s options and its nodes' parameters, ROS-free.

- The parser (`build_parser`) is generated: every parameter of `fleet.parameters` with an
  `Option` is an option (flag, help, the table's default, type and choices), beside the few
  options that are not node parameters (`LAUNCH_OPTIONS`: process layout, namespace, bag, ...).
- Every node's parameters are resolved once (`plan_parameters`, `plan_policy_parameters`:
  defaults < params file < options < `--ros-args -p`), each value checked once at this boundary
  (one line each, `UpError`), an option given where it does not apply refused (`Option.applies`
  against `UpFacts`, what the run will be), into an immutable `Plan`.
`ros.launcher.prepare` adds what needs the ROS side or the networks (the checkpoint loads, the
bag recorder) and starts the processes."""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

from mapf_fleet.fleet import parameters as P
# the process layout's limits and checks (fleet.layout), part of `up`'s API
from mapf_fleet.fleet.layout import (LARGE_FLEET_PROCESSES, LARGE_FLEET_ROBOTS,  # noqa: F401
                                     MAX_DISCOVERED_PROCESSES, MAX_NODES_PER_PROCESS,
                                     layout_problem, layout_warning, policy_processes,
                                     recommended_nodes_per_process)

# the user's help text of `mapf-fleet up`
DESCRIPTION = """`mapf-fleet up`: start a simulated fleet (simulator + one policy node per robot), show live
progress, print the outcome and exit 0 on success.

Process layout: `--nodes-per-process K` hosts K robots' nodes per process; without it `up`
chooses K from the robot count and the memory available and says so (a process per robot up to
~32 processes, Fast DDS discovery on loopback; from 256 robots 8 processes, K = ceil(robots / 8),
e.g. 64 for 512: the layouts measured to get ready; fewer, larger processes when memory is
short); a given layout that would not fit in memory is refused;
`--single-process` runs the simulator and every policy node in this process. The policy nodes of
one process share one hub (one subscription per shared topic, batched inference). With
`--real-robots` the aggregator replaces the simulator: the robots publish their own poses on
/robot_<i>/pose and follow /robot_<i>/waypoint. Every process gets
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST.

The simulator (or the aggregator) arbitrates each tick with `--conflict-rule`: `pibt_anchor_swap_lns`
(default: PIBT over the robots' ranked actions with the top-priority robot on its distance order
and lacam3's swap in corridors, each robot's first move taken from a plan of the next 16 ticks
repaired every tick; nothing is reverted), `pibt_anchor_swap` (the same, one tick at a time),
`pibt_anchor` (without swap), `pibt_anchor_swap_epibt` (3-move operations),
`pibt` (CS-PIBT as published), the other `_swap` / `_hindrance` variants, `lacam` (a kept LaCAM
plan over the robots' rankings, repaired when something leaves it, `--planning-budget` seconds per
tick, else the `pibt_anchor_swap` step) or `revert` (the paper's environment: conflicting first choices
are reverted).

With no arguments: 8 simulated robots on a generated 16x16 map, checkpoint models/default.pt.
"""


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


# `up`'s options that set no node parameter (argparse keyword arguments, in help order)
LAUNCH_OPTIONS = {
    "--preference-mode": dict(dest="preference_mode", choices=P.RANKINGS, default=None,
                              help="deprecated spelling of --ranking"),
    "--nodes-per-process": dict(type=int, default=1, help=(
        "robots' policy nodes hosted per process (one hub each; default: chosen from the robot "
        "count and the memory available, and said in one line: a process per robot for small "
        "fleets, 8 processes from 256 robots, fewer when memory is short)")),
    "--single-process": dict(action="store_true",
                             help="simulator and all policy nodes in this process"),
    "--real-robots": dict(action="store_true", help=(
        "real-robot mode: the aggregator (robots' own /robot_<i>/pose feeds) instead of the "
        "simulator")),
    "--bag": dict(default="", metavar="DIR", help=(
        "also record the fleet's topics into the new rosbag2 DIR (MCAP; `mapf-fleet record "
        "DIR` started beside the fleet, closed at the end)")),
    "--log-dir": dict(default="", metavar="DIR", help=(
        "keep the policy processes' logs in DIR (created if needed; default: a temporary "
        "directory, removed after a successful run and kept, with its path printed, after a "
        "failed one)")),
    "--domain-id": dict(type=int, default=None,
                        help="ROS_DOMAIN_ID to use, 0-232 (default: the environment's)"),
    "--params-file": dict(default="", help=(
        "ROS parameters YAML for the nodes (config/fleet/fleet.yaml shows every parameter); "
        "the options above and --ros-args -p win over it")),
    "--namespace": dict(default="", help=(
        "ROS namespace of the whole fleet (e.g. /fleet_a: topics /fleet_a/fleet/state, "
        "/fleet_a/robot_0/pose, ...), so fleets in different namespaces share a ROS_DOMAIN_ID; "
        "same as --ros-args -r __ns:=/fleet_a")),
    "--quiet": dict(action="store_true", help="no live progress"),
}


@dataclass(frozen=True)
class TableOption:
    """One node parameter `up` sets from an option: the node kind ('sim': the simulator or the
    aggregator; 'policy'), the parameter's name and its `Param` (with its `Option`)."""
    kind: str
    name: str
    param: P.Param

    @property
    def option(self) -> P.Option:
        return self.param.option

    @property
    def dest(self) -> str:
        return self.option.flag.lstrip("-").replace("-", "_")


def table_options() -> list[TableOption]:
    """Every (node kind, parameter) an `up` option sets, in table order (the simulator's, the
    aggregator's, the policy nodes'); a parameter shared by the tables once per kind."""
    out, seen = [], set()
    for kind, table in (("sim", P.SIMULATOR), ("sim", P.AGGREGATOR), ("policy", P.POLICY)):
        for name, param in table.items():
            if param.option is not None and (kind, name) not in seen:
                seen.add((kind, name))
                out.append(TableOption(kind, name, param))
    return out


def option_help(param: P.Param) -> str:
    """An option's help: its own text or the parameter's description, and the table's default
    unless the text states one (or the default is empty)."""
    text = param.option.help or param.description
    if "default" in text or param.default in ("", None) or param.default is False:
        return text
    return f"{text} (default: {param.default})"


def build_parser() -> argparse.ArgumentParser:
    """`up`'s options: one per `Option` of the parameter tables (default None: not given, the
    parameter's value comes from its table, a params file or -p; the help states the table's
    default), then `LAUNCH_OPTIONS`."""
    parser = argparse.ArgumentParser(prog="mapf-fleet up", description=DESCRIPTION,
                                     formatter_class=_HelpFormatter)
    declared = set()
    for entry in table_options():
        option, param = entry.option, entry.param
        if option.flag in declared or option.part not in (None, 0):
            continue  # one option for the parameters it sets (--origin X Y)
        declared.add(option.flag)
        kwargs = dict(default=None, help=option_help(param))
        if param.type in (int, float):
            kwargs["type"] = param.type
        choices = tuple(c for c in param.choices if c != "")
        if choices and option.nargs is None:
            kwargs["choices"] = choices
        if option.metavar is not None:
            kwargs["metavar"] = option.metavar
        if option.nargs is not None:
            kwargs["nargs"] = option.nargs
        parser.add_argument(option.flag, **kwargs)
    for flag, kwargs in LAUNCH_OPTIONS.items():
        parser.add_argument(flag, **kwargs)
    return parser


MAX_DOMAIN_ID = 232  # the largest ROS_DOMAIN_ID whose Fast DDS ports are valid
# a ROS namespace: tokens of letters, digits and _, none starting with a digit
NAMESPACE_RE = re.compile(r"/?([A-Za-z_][A-Za-z0-9_]*)(/[A-Za-z_][A-Za-z0-9_]*)*/?")


class UpError(ValueError):
    """A value `up` refuses before anything starts: one line, exit 2."""


def _is_up_option(arg: str) -> bool:
    option = arg.split("=", 1)[0]
    return option.startswith("--") and any(
        option in a.option_strings for a in build_parser()._actions)


def _readonly(values: dict) -> MappingProxyType:
    return MappingProxyType({node: MappingProxyType(dict(v)) for node, v in values.items()})


@dataclass(frozen=True)
class Plan:
    """What `up` starts, resolved once and every value checked: the nodes' parameters ({node
    name: {name: value}}, read-only) and where each came from, the fleet's namespace, the ROS
    arguments passed on as they are, the warnings to print and the merged params file the
    nodes read (`with_run_files`). Built by `PlanDraft.freeze`."""
    sim_name: str
    values: MappingProxyType
    origin: MappingProxyType
    namespace: str
    passed: tuple
    warnings: tuple = ()
    params_path: str = ""

    @property
    def sim(self):
        return self.values[self.sim_name]

    @property
    def policy(self):
        return self.values.get("mapf_policy_0", MappingProxyType({}))

    @property
    def guidance(self) -> str | None:
        """The guidance file every node of the fleet builds its distances with (None: none)."""
        return P.resolve_guidance(self.sim["guidance"])

    @property
    def device(self) -> str:
        """Where the policy nodes run inference, as given (auto, cpu, cuda)."""
        return self.policy.get("device", P.POLICY["device"].default)

    def with_run_files(self, record_file: str | None = None, params_path: str = "") -> "Plan":
        """This plan with the run's record (when given) and the merged params file's path."""
        values = {node: dict(v) for node, v in self.values.items()}
        if record_file is not None:
            values[self.sim_name]["record_file"] = record_file
        return dataclasses.replace(self, values=_readonly(values),
                                   params_path=params_path or self.params_path)

    def ros_args(self) -> list[str]:
        """A node's ROS arguments: the fleet's namespace and the merged params file."""
        out = ["--ros-args"]
        if self.namespace.strip("/"):
            out += ["-r", f"__ns:=/{self.namespace.strip('/')}"]
        if self.params_path:
            out += ["--params-file", self.params_path]
        return out + list(self.passed)


@dataclass
class PlanDraft:
    """A `Plan` while `up` resolves it (the simulator's values first, the policy nodes' once the
    instance gives the robot count); `freeze()` makes the plan."""
    sim_name: str
    values: dict
    origin: dict
    namespace: str
    passed: list
    warnings: list = field(default_factory=list)

    @property
    def sim(self) -> dict:
        return self.values[self.sim_name]

    @property
    def policy(self) -> dict:
        return self.values.get("mapf_policy_0", {})

    def freeze(self) -> Plan:
        return Plan(self.sim_name, _readonly(self.values), _readonly(self.origin),
                    self.namespace, tuple(self.passed), tuple(self.warnings))


def _given(args, entry: TableOption):
    """The value the command line gives `entry`'s parameter (None: not given)."""
    value = getattr(args, entry.dest, None)
    if isinstance(value, (list, tuple)):
        part = entry.option.part or 0
        return value[part] if part < len(value) else None
    return value if not entry.option.part else None


def explicit_options(args) -> dict:
    """{node kind: {parameter: (value, option)}} of the options given on the command line."""
    out = {"sim": {}, "policy": {}}
    for entry in table_options():
        value = _given(args, entry)
        if value is not None and value != "":
            out[entry.kind][entry.name] = (value, entry.option.flag)
    return out


@dataclass(frozen=True)
class UpFacts:
    """What the run will be, as the options' `Applies` rules read it (the resolved values)."""
    real_robots: bool
    nav2_map: bool
    instance: str
    map: str
    task_source: str


def options_not_applying(args, sim: dict) -> str:
    """The first option given that the run (`sim`: the simulator's or aggregator's resolved
    values) would not use ("" when none)."""
    map_file = str(sim.get("map_file", ""))
    facts = UpFacts(bool(args.real_robots), map_file.lower().endswith((".yaml", ".yml")),
                    str(sim.get("instance_file", "")), map_file, str(sim.get("task_source", "")))
    if facts.instance and facts.map:
        return "--instance and --map: give one of them"
    for entry in table_options():
        if _given(args, entry) is None:
            continue
        for rule in entry.option.applies:
            if not rule.test(facts):
                return f"{entry.option.flag} {rule.refusal}"
    return ""


def plan_parameters(args, ros_argv: list[str]) -> PlanDraft:
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
    not_applying = options_not_applying(args, sim)
    if not_applying:
        raise UpError(not_applying)
    if origin[sim_name]["max_steps"] == "default" and sim["task_source"] == "external":
        sim["max_steps"] = 0  # external goals come when they come: no tick limit
    if sim["max_steps"] == 0 and sim["task_source"] == "instance":
        where = origin[sim_name]["max_steps"]
        raise UpError(f"{where}: max_steps must be >= 1 with task_source instance (0, no limit, "
                      f"is for the continuous sources lifelong, tasks, external), got 0"
                      .replace("--max-steps: max_steps", "--max-steps"))
    if sim["task_source"] == "tasks" and not sim["task_file"]:
        raise UpError("task_source tasks needs a task file: --task-source tasks FILE")
    entries = table_options()
    policy_options = {e.name for e in entries if e.kind == "policy"}
    for entry in entries:  # (an option of the policy nodes too stays as given, for them)
        if (entry.kind == "sim" and entry.name in sim and entry.option.nargs is None
                and entry.name not in policy_options):
            setattr(args, entry.dest, sim[entry.name])
    args.task_source, args.task_file = sim["task_source"], sim["task_file"] or None
    args.namespace = namespace
    return PlanDraft(sim_name, values, origin, namespace, ros.passed, warnings)


def plan_policy_parameters(plan: PlanDraft, args, ros_argv: list[str], num_robots: int,
                           checkpoint: str) -> Plan:
    """The policy nodes' resolved parameters into `plan` (a parameter they share with the
    simulator, e.g. conflict_rule, guidance, follows the simulator's unless set for them; the
    checkpoint defaults to `checkpoint`); the plan, frozen."""
    ros = P.read_ros_args(ros_argv, _is_up_option)
    names = [f"mapf_policy_{i}" for i in range(num_robots)]
    user_files = [args.params_file] if args.params_file else []
    shared = {name: plan.sim[name] for name in P.POLICY if name in plan.sim}
    defaults = {"policy": {**shared, "checkpoint": checkpoint}}
    options = explicit_options(args)
    try:
        values, origin, warnings = P.merged_values([plan.sim_name] + names, plan.namespace,
                                                   user_files, options, ros, defaults)
    except ValueError as exc:
        raise UpError(str(exc)) from None
    for name in names:
        plan.values[name] = values[name]
        plan.origin[name] = origin[name]
        if values[name]["guidance"] != plan.sim["guidance"]:  # one map of costs for all
            raise UpError(
                f"guidance differs between nodes: {plan.sim_name} {plan.sim['guidance']!r} "
                f"({plan.origin[plan.sim_name]['guidance']}), {name} "
                f"{values[name]['guidance']!r} ({origin[name]['guidance']}); give every node "
                f"the same (--guidance FILE)")
    plan.warnings += [w for w in warnings if w not in plan.warnings]
    if num_robots >= LARGE_FLEET_ROBOTS and plan.origin[plan.sim_name].get(
            "robot_actions") == "default":
        # every process discovers every per-robot action server's 8 endpoints: in a large fleet
        # they slow both start-up and ticks (docs/results.md, "Process layouts"), so it leaves
        # them out
        plan.sim["robot_actions"] = False
        plan.warnings.append(
            f"note: {num_robots} robots: no per-robot robot_<i>/navigate_to_pose action servers "
            f"(goals: fleet/navigate_to_pose with the robot in the goal, `mapf-fleet goal`, "
            f"robot_<i>/goal_pose, fleet/submit_tasks); -p robot_actions:=true serves them")
    return plan.freeze()


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
    """The problem ("" when none) of `--task-source SOURCE [FILE]` (its parts go to the
    parameters task_source and task_file)."""
    from mapf_fleet.fleet.tasks import TASK_SOURCES

    if args.task_source is None:
        return ""
    source, rest = args.task_source[0], args.task_source[1:]
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
