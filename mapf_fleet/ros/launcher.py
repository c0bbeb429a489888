"""`mapf-fleet up`: check its options and its nodes' parameters (`prepare`: the ROS-free plan of
`mapf_fleet.fleet.up_options`, plus the checkpoint and the instance it loads), start the fleet's
processes, supervise them, show live progress, print the outcome and exit 0 on success."""

from __future__ import annotations

import contextlib
import glob
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from mapf_fleet.fleet import parameters as P
from mapf_fleet.fleet.instances import InstanceSource
from mapf_fleet.fleet.up_options import (MAX_DISCOVERED_PROCESSES, MAX_NODES_PER_PROCESS, UpError,
                                         build_parser, default_robot_count, layout_problem,
                                         layout_warning, plan_parameters, plan_policy_parameters,
                                         policy_processes, policy_value, record_problem,
                                         unknown_as_free_warning)
from mapf_fleet.paths import data_root
from mapf_fleet.ros import common
from mapf_fleet.ros.layout_choice import (available_memory_mb, choose_layout,
                                          layout_memory_problem, map_size_problem)

# `up`'s API (its options live in fleet.up_options, re-exported here)
__all__ = ["DATA_ROOT", "DEFAULT_CHECKPOINT", "MAX_DISCOVERED_PROCESSES", "MAX_NODES_PER_PROCESS",
           "UpError", "build_parser", "checked_checkpoint", "default_checkpoint",
           "layout_problem", "layout_warning", "main", "policy_processes", "prepare", "report"]

# where models/ lives: the install's share/mapf_fleet, else the checkout
DATA_ROOT = data_root("models")
DEFAULT_CHECKPOINT = DATA_ROOT / "models" / "default.pt"


def default_checkpoint() -> str:
    """models/default.pt if present, else the first DHC (or any) checkpoint in models/."""
    if DEFAULT_CHECKPOINT.is_file():
        return str(DEFAULT_CHECKPOINT)
    found = sorted(glob.glob(str(DATA_ROOT / "models" / "*.pt")))
    preferred = [f for f in found if "dhc" in Path(f).name.lower()] or found
    return preferred[0] if preferred else ""


def prepare(argv: list[str]):
    """(args, plan (`up_options.Plan`, immutable), robot count) of `up` with every value
    checked, nothing started; UpError (one line) for anything refused."""
    own, ros_argv = common.split_ros_args(argv)
    parser = build_parser()
    parser.set_defaults(nodes_per_process=None)  # not given: chosen below (`choose_layout`)
    args = parser.parse_args(own)
    layout_given = args.nodes_per_process is not None
    budget_given = args.planning_budget is not None  # (plan_parameters fills the defaults in)
    if layout_given and args.single_process:
        raise UpError("--nodes-per-process applies to policy processes; --single-process hosts "
                      "every node in up's own process: give one of them")
    if not layout_given:
        args.nodes_per_process = 1  # for the checks of plan_parameters; chosen below
    plan = plan_parameters(args, ros_argv)
    rule = plan.sim.get("conflict_rule")
    if budget_given and rule != "lacam":
        raise UpError(f"--planning-budget applies to --conflict-rule lacam only (the conflict "
                      f"rule is {rule}): drop it or add --conflict-rule lacam")
    if args.record:
        problem = record_problem(args.record)
        if problem:
            raise UpError(problem)
    elif plan.origin[plan.sim_name]["record_file"] != "default":
        problem = record_problem(plan.sim["record_file"],
                                 plan.origin[plan.sim_name]["record_file"] + ": record_file")
        if problem:
            raise UpError(problem)
    given = args.checkpoint
    if given is None:
        policy_checkpoint = policy_value(args, ros_argv, "checkpoint")
        given = policy_checkpoint or None
    checkpoint = given or default_checkpoint()
    if not checkpoint or not Path(checkpoint).is_file():
        if given:
            problem = f"checkpoint not found: {given!r}"
        else:
            problem = f"no checkpoint in {DATA_ROOT / 'models'} (default {DEFAULT_CHECKPOINT.name})"
        raise UpError(f"{problem}. Pass --checkpoint FILE.pt (a file written by "
                      f"mapf_fleet.models.save_checkpoint, e.g. by training), or put one at "
                      f"{DEFAULT_CHECKPOINT}.")
    if args.real_robots and args.single_process:
        raise UpError("--real-robots runs the aggregator in its own process; drop "
                      "--single-process")
    problem, metadata = checked_checkpoint(checkpoint)
    if problem:  # before anything starts: the policy processes would die one by one
        raise UpError(problem)
    sim = plan.sim
    if plan.origin[plan.sim_name]["guidance"] == "default":
        # the guidance the checkpoint was trained for (metadata field guidance,
        # `models.checkpoint`), as `evaluate` reads it (one default); none: the fleet's
        recorded = None if metadata.get("guidance") is None else str(metadata["guidance"])
        if recorded is not None:
            problem = P.GUIDANCE.problem(recorded)
            if problem:
                raise UpError(f"{checkpoint}: its metadata field guidance: {problem}; pass "
                              f"--guidance")
            sim["guidance"] = recorded
    available = available_memory_mb()
    if not (sim["instance_file"] or sim["map_file"]):  # before the map takes the memory
        problem = map_size_problem(int(sim["size"]), available)
        if problem:
            raise UpError(problem)
    try:
        if plan.origin[plan.sim_name]["num_robots"] == "default":
            sim["num_robots"] = args.num_robots = default_robot_count(args)
        source = InstanceSource(sim["instance_file"], sim["map_file"], sim["scen_file"],
                                sim["num_robots"], sim["size"], sim["density"], sim["seed"],
                                sim["cell_size"])
        instance = source.load()
        num_robots = instance.num_agents
    except (ValueError, OSError) as exc:
        raise UpError(f"bad instance: {exc}") from None
    except MemoryError:
        raise UpError(f"the instance does not fit in memory (size {sim['size']}, "
                      f"{sim['num_robots']} robots): use a smaller --size or map") from None
    if layout_given or args.single_process:
        problem = layout_memory_problem(num_robots, args.single_process,
                                        args.nodes_per_process, available)
        if problem:
            raise UpError(problem)
    else:
        args.nodes_per_process, args.layout_note = choose_layout(num_robots, available,
                                                                 recorder=bool(args.bag))
    warning = unknown_as_free_warning(sim["map_file"])
    if warning:
        plan.warnings.append(warning)
    if args.bag:  # tick 0 waits until the hubs and the recorder hear the state: no tick missed
        # (the recorder subscribes to it once it has matched every hub: bag_recording)
        from mapf_fleet.ros.bag import RECORDER_NODE

        sim["state_subscribers"] = (
            policy_processes(num_robots, args.single_process, args.nodes_per_process) + 1)
        sim["state_recorder"] = RECORDER_NODE
    if sim["task_file"]:  # a bad or unreachable task: one line naming file, line, task, field
        from mapf_fleet.fleet.tasks import TaskFileError, load_task_file

        geometry = common.MapGeometry(*(source.geometry() or (
            sim["resolution"], sim.get("origin_x", 0.0), sim.get("origin_y", 0.0))))
        try:
            load_task_file(sim["task_file"], num_robots=num_robots, cell_of=geometry.xy_to_cell,
                           grid=instance.grid, starts=instance.starts)
        except TaskFileError as exc:
            raise UpError(str(exc)) from None
    problem = layout_problem(num_robots, args.single_process, args.nodes_per_process)
    if problem:
        raise UpError(problem)
    if args.bag and Path(args.bag).exists():
        raise UpError(f"--bag {args.bag} exists already: a rosbag2 is written into a new "
                      f"directory")
    plan = plan_policy_parameters(plan, args, ros_argv, num_robots, checkpoint)  # frozen
    try:  # device cuda without one: refused here, not by every policy process
        common.resolve_device(plan.device)
    except ValueError as exc:
        raise UpError(str(exc)) from None
    return args, plan, num_robots


def checked_checkpoint(path: str) -> tuple[str, dict]:
    """("", its metadata) when `path` loads as a policy (as the policy nodes load it), else
    (the reason, {}), e.g. "bad.pt: not a readable checkpoint (corrupt, truncated or not
    weights-only): ..."; the file is read once."""
    from mapf_fleet.models.checkpoint import load_checkpoint

    try:
        _, metadata = load_checkpoint(path)
    except (ValueError, OSError) as exc:  # CheckpointError is a ValueError
        return (str(exc).strip().splitlines()[0] if str(exc).strip() else repr(exc)), {}
    return "", metadata


START_MARGIN_S = 120.0  # a process's own start-up (imports, DDS) on a loaded machine
OUTCOME_WAIT_S = 15.0  # longest wait at the end for the bag recorder to write the outcome


def main(argv: list[str] | None = None) -> int:
    from mapf_fleet.ros.processes import stop_signals

    signals = stop_signals()  # first thing: SIGINT / SIGTERM while loading are kept, no traceback
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args, plan, num_robots = prepare(argv)
    except UpError as exc:  # before anything starts (a node would refuse it, some only late)
        print(f"mapf-fleet up: {exc}", file=sys.stderr)
        return 2
    for warning in plan.warnings:
        print(f"mapf-fleet up: {warning}", file=sys.stderr)
    if getattr(args, "layout_note", ""):
        print(f"mapf-fleet up: {args.layout_note}", file=sys.stderr)
    warning = layout_warning(num_robots, args.single_process, args.nodes_per_process,
                             recorder=bool(args.bag))
    if warning:
        print(f"mapf-fleet up: {warning}", file=sys.stderr)
    from mapf_fleet.ros.processes import remove_stale_shm

    remove_stale_shm()  # an empty port file left by a killed run freezes every later fleet
    env = common.prepare_environment(dict(os.environ))
    if args.domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(args.domain_id)
    # the default record, the merged parameters and the policy processes' logs (in --log-dir
    # when given); removed when `up` ends after a successful run, kept after a failed one
    work = tempfile.mkdtemp(prefix="mapf_fleet_")
    args.work_dir = args.log_dir or work
    if args.log_dir:
        try:
            os.makedirs(args.log_dir, exist_ok=True)
        except OSError as exc:
            print(f"mapf-fleet up: --log-dir {args.log_dir}: {exc.strerror or exc}",
                  file=sys.stderr)
            return 2
    plan = plan.with_run_files(
        record_file=None if plan.sim["record_file"] else os.path.join(work, "run.json"),
        params_path=os.path.join(work, "parameters.yaml"))
    record = plan.sim["record_file"]
    P.write_params_file(plan.params_path, plan.values, plan.namespace)
    started = time.monotonic()
    result = 1
    try:
        if args.single_process:
            os.environ.update(env)
            code, problem = run_single_process(num_robots, plan, args)
        else:
            code, problem = run_processes(num_robots, plan, args, env)
        elapsed = time.monotonic() - started
        result = finish(code, problem, record, elapsed, record != os.path.join(work, "run.json"))
        return result
    finally:
        # a run stopped by the user (Ctrl-C, SIGTERM: 130 / 143) did not fail: nothing to keep
        keep_logs(work, args.log_dir, failed=result not in (0, 130, 143))
        if result != 0 and not args.single_process:  # children may have been killed
            from mapf_fleet.ros.processes import clean_zombie_shm

            clean_zombie_shm()
        # the handlers stay to the process's exit (not restored): a signal that comes while
        # `up` returns, its children already stopped, is no KeyboardInterrupt traceback (only
        # Python's own finalization resets them)


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


def finish(code: int, problem: str, record: str, elapsed: float, keep_record: bool) -> int:
    """`up`'s exit code after its run: the outcome's (0 success, 1 failure), 128 + the signal
    that stopped it (130 / 143, the outcome "stopped at tick k" still reported), 1 when a
    process of the fleet died (`problem`), or the simulator's own error code (2: it refused its
    parameters, with its message above)."""
    if code not in (0, 1) and code < 128 and not problem:
        return code
    from mapf_fleet.fleet.record import journal_path

    if code >= 128 and not Path(record).exists() and not Path(journal_path(record)).exists():
        print(f"mapf-fleet up: stopped by signal {code - 128} before the run started",
              file=sys.stderr)
        return code
    result = report(record, elapsed, keep_record)
    if code >= 128:
        return code
    return 1 if problem else result


def run_processes(num_robots, plan, args, env) -> tuple[int, str]:
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
    with bag_recording(args, env, signals, recorder_expectations(num_robots, plan, args),
                       float(plan.sim["startup_timeout"])) as recorder:
        if recorder is False:
            return (signals.exit_code or 2), ""
        children: list[Child] = []
        try:
            k = args.nodes_per_process
            for first in range(0, num_robots, k):
                ids = f"{first}-{min(first + k, num_robots) - 1}"
                children.append(Child(
                    f"policy process (robots {ids})",
                    runner + ["policy", "--robots", ids] + plan.ros_args(),
                    env, log_path=os.path.join(args.work_dir, f"policy_{ids}.log")))
            name = "aggregator" if args.real_robots else "simulator"
            echo = None if args.quiet else (lambda line: print(line, flush=True))
            main = Child(name, runner + [name] + plan.ros_args(), env,
                         echo=echo)
        except BaseException:
            stop_children(children)
            raise
        from mapf_fleet.fleet.record import journal_path

        record = plan.sim["record_file"]
        started = (lambda: os.path.exists(journal_path(record))  # noqa: E731
                   or os.path.exists(record))
        # the run starts within startup_timeout of the simulator's start (robots not ready
        # then: it starts without them), plus its start-up on a loaded machine
        deadline = float(plan.sim["startup_timeout"]) + START_MARGIN_S
        code, problem = supervise(main, children, signals, echoed=not args.quiet,
                                  watched=[recorder] if recorder else [], running=started,
                                  start_deadline=deadline)
        if recorder:  # the simulator published its outcome: the recorder is waited for
            recorder.fleet_ended = code in (0, 1) and not problem
    if signals.requested:
        return signals.exit_code, problem
    return (1 if problem else code), problem


def recorder_expectations(num_robots: int, plan, args) -> dict[str, int]:
    """The publishers the bag recorder matches before it subscribes to the fleet state, which
    tick 0 waits for (`bag.BagRecorder`, the simulator's `state_recorder`): every policy
    process's moves (one publisher per process: /fleet/move_batches, or /fleet/moves with
    per_robot_messages) and the simulator's (aggregator's) progress, in the fleet's namespace."""
    per_robot = bool(plan.policy.get("per_robot_messages", False))
    moves = common.MOVES_TOPIC if per_robot else common.MOVE_BATCHES_TOPIC
    processes = policy_processes(num_robots, args.single_process, args.nodes_per_process)
    return {common.in_namespace(moves, plan.namespace): processes,
            common.in_namespace(common.PROGRESS_TOPIC, plan.namespace): 1}


@contextlib.contextmanager
def bag_recording(args, env, signals, expect: dict[str, int] | None = None,
                  expect_timeout: float = 120.0, ready_timeout: float = 120.0):
    """With `--bag DIR`: the rosbag2 recorder (`mapf_fleet.ros.bag`, `mapf-fleet record DIR` in
    the fleet's namespace) as a child process, started before the fleet and ready (its
    subscriptions exist) before the fleet starts; it subscribes to the fleet state, which tick
    0 waits for, only once it has matched the publishers of `expect` ({topic: count},
    `recorder_expectations`) or after `expect_timeout` s, so the bag misses no tick's message;
    stopped after the fleet with `bag.stop_recorder` (the last messages in flight, then SIGINT:
    the bag is closed). Yields the recorder's `processes.Child`, None without --bag, False
    when it could not start (its output is shown)."""
    if not getattr(args, "bag", ""):
        yield None
        return
    import threading

    from mapf_fleet.ros.bag import (OUTCOME_PREFIX, READY_PREFIX, recorder_command,
                                    stop_recorder)
    from mapf_fleet.ros.processes import Child

    namespace = args.namespace
    ready = threading.Event()

    outcome = threading.Event()

    def echo(line: str) -> None:
        if line.startswith(READY_PREFIX):
            ready.set()
        elif line.startswith(OUTCOME_PREFIX):
            outcome.set()
        elif not args.quiet or line.startswith("mapf-fleet record:"):
            print(line, flush=True)

    recorder = Child("bag recorder", recorder_command(args.bag, namespace=namespace or "",
                                                      expect=expect,
                                                      expect_timeout=expect_timeout),
                     env, echo=echo)
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
        # the recorder announces the outcome once it and the final state (`done`) are written:
        # then every tick is in (a loaded machine may take seconds to deliver a short run's)
        if getattr(recorder, "fleet_ended", False):
            outcome.wait(OUTCOME_WAIT_S)
        code = stop_recorder(recorder.proc)
        recorder.wait_output()
        if code != 0:
            print(f"mapf-fleet up: {recorder.report()}", file=sys.stderr)


def run_single_process(num_robots, plan, args) -> tuple[int, str]:
    """The simulator and every policy node in this process (with --bag, the recorder beside it
    as a child process). (exit code, problem) as `run_processes`."""
    from mapf_fleet.ros.processes import stop_signals

    signals = stop_signals()
    with bag_recording(args, dict(os.environ), signals,
                       recorder_expectations(num_robots, plan, args),
                       float(plan.sim["startup_timeout"])) as recorder:
        if recorder is False:
            return (signals.exit_code or 2), ""
        code, problem = _run_in_this_process(num_robots, plan, args)
        if recorder:
            recorder.fleet_ended = code in (0, 1) and not problem
        return code, problem


def _run_in_this_process(num_robots, plan, args) -> tuple[int, str]:
    import rclpy

    from mapf_fleet.ros.common import init_process
    from mapf_fleet.ros.policy_node import make_policy_nodes, spin_policy_nodes
    from mapf_fleet.ros.simulator_node import SimulatorNode

    # the same ROS arguments (and precedence) as the processes get, for every node of this one
    # SIGINT / SIGTERM stop the simulator's run (record, "stopped at tick k"): exit 130 / 143
    signals = init_process(["up"] + plan.ros_args())
    try:
        simulator = SimulatorNode()
        policies = make_policy_nodes(list(range(num_robots)))
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
    from mapf_fleet.fleet.record import complete_record

    try:  # a simulator killed mid-run leaves its journal: every tick it ran, into the record
        record = complete_record(record_path)
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
