"""`mapf-fleet node NAME [--ros-args ...]`: run one node like `ros2 run mapf_fleet NAME`.

NAME is simulator, policy or aggregator. `mapf-fleet node policy --robots 0-7 --ros-args -p
checkpoint:=F` hosts several policy nodes in one process (one executor, spun in one thread), which is
how large fleets stay within Fast DDS's ~32 processes per domain.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mapf_fleet.ros import common

NODES = {
    "simulator": "mapf_fleet.ros.simulator_node",
    "policy": "mapf_fleet.ros.policy_node",
    "aggregator": "mapf_fleet.ros.aggregator_node",
}


def parse_robot_ids(text: str) -> list[int]:
    """'0-3,7' -> [0, 1, 2, 3, 7]."""
    ids: list[int] = []
    try:
        for part in text.split(","):
            if "-" in part:
                low, high = part.split("-")
                ids.extend(range(int(low), int(high) + 1))
            elif part.strip():
                ids.append(int(part))
    except ValueError:
        raise ValueError(f"--robots: expected ids like '0-3,7', got {text!r}") from None
    if not ids or min(ids) < 0:
        raise ValueError(f"--robots: expected non-negative ids, got {text!r}")
    return ids


def params_files(ros_args: list[str]) -> list[str]:
    """The `--params-file` paths named in ROS arguments; FileNotFoundError for a missing one
    (rcl's own message names its parser's source lines instead)."""
    found = [ros_args[i + 1] for i, arg in enumerate(ros_args[:-1]) if arg == "--params-file"]
    for path in found:
        if not Path(path).is_file():
            raise FileNotFoundError(f"params file not found: {path}")
    return found


def host_policy_nodes(robot_ids: list[int], ros_args: list[str]) -> int:
    import rclpy

    from mapf_fleet.ros.common import init_process
    from mapf_fleet.ros.policy_node import make_policy_nodes, spin_policy_nodes

    signals = init_process(["policy"] + ros_args)  # SIGINT / SIGTERM: exit 130 / 143
    try:
        return spin_policy_nodes(make_policy_nodes(robot_ids), signals=signals)
    finally:
        rclpy.try_shutdown()
        signals.restore()


def main(argv: list[str] | None = None) -> int:
    from mapf_fleet.ros.processes import stop_signals

    stop_signals()  # first thing: a SIGINT / SIGTERM while the node loads is kept (exit 130 / 143)
    argv = list(sys.argv[1:] if argv is None else argv)
    own, ros_args = common.split_ros_args(argv)
    parser = argparse.ArgumentParser(prog="mapf-fleet node", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", choices=sorted(NODES))
    parser.add_argument("--robots", help="policy only: host these robot ids in this process")
    parser.add_argument("--params-file", help="ROS parameters YAML (same as --ros-args "
                        "--params-file F)")
    args = parser.parse_args(own)
    if args.params_file:
        ros_args = (ros_args or ["--ros-args"]) + ["--params-file", args.params_file]
    params_files(ros_args)
    common.prepare_environment()
    if args.robots:
        if args.name != "policy":
            parser.error("--robots applies to the policy node only")
        return host_policy_nodes(parse_robot_ids(args.robots), ros_args)
    import importlib

    return int(importlib.import_module(NODES[args.name]).main(ros_args) or 0)


if __name__ == "__main__":
    from mapf_fleet.entry import run_main

    sys.exit(run_main(f"mapf-fleet node {sys.argv[1] if len(sys.argv) > 1 else ''}".rstrip(),
                      main))
