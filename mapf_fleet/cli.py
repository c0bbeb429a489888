"""The `mapf-fleet` command: one entry point for what `ros2 run/launch/topic echo` and the
research scripts would do. Sub-commands import their layer lazily, so `mapf-fleet evaluate`
never loads rclpy and `mapf-fleet demo` never loads torch."""

from __future__ import annotations

import importlib
import sys

# sub-command -> (module, function, one-line help). Each function takes argv (list[str]) and
# returns an exit code.
COMMANDS = {
    "demo": ("mapf_fleet.grid.demo", "main", "grid-world demo with the non-learned policy"),
    "train": ("mapf_fleet.training.cli", "main", "Ape-X training with both curricula"),
    "dagger": ("mapf_fleet.training.dagger", "main", "DAgger behind the arbiter, LaCAM labels"),
    "evaluate": ("mapf_fleet.evaluation.cli", "main", "the paper's evaluation protocol"),
    "render": ("mapf_fleet.view.replay", "main",
               "an episode, or a fleet's recorded run (--run JSON/rosbag), as GIF/WebP"),
    "card": ("mapf_fleet.evaluation.model_card", "main", "write a checkpoint's model card"),
    "guidance": ("mapf_fleet.evaluation.guidance_opt", "main",
                 "learned guidance (CMA-ES, resumable) and guidance files for a map"),
    "up": ("mapf_fleet.ros.launcher", "main", "start a simulated (or real-robot) fleet"),
    "echo": ("mapf_fleet.ros.echo", "main", "print a topic's messages as YAML"),
    "topics": ("mapf_fleet.ros.echo", "topics_main", "list the fleet's topics"),
    "record": ("mapf_fleet.ros.bag", "main", "record the fleet's topics into a rosbag2 (MCAP)"),
    "view": ("mapf_fleet.view.live", "main", "live picture of a running fleet in a browser"),
    "node": ("mapf_fleet.ros.run", "main", "run one node, like `ros2 run mapf_fleet <node>`"),
    "param": ("mapf_fleet.ros.param_cli", "main",
              "get, set or list a running node's parameters, like `ros2 param`"),
    "goal": ("mapf_fleet.ros.goal_cli", "main",
             "send a robot a goal (navigate_to_pose, goal_pose, or tasks for any idle robot)"),
}


def _usage() -> str:
    lines = ["usage: mapf-fleet <command> [options]", "", "commands:"]
    for name, (_, _, text) in COMMANDS.items():
        lines.append(f"  {name:<10} {text}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"mapf-fleet: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module, func, _ = COMMANDS[name]
    from mapf_fleet.entry import run_main

    # a user error (bad file, field or value) is one line on stderr and exit 2, no traceback
    return run_main(f"mapf-fleet {name}",
                    lambda args: getattr(importlib.import_module(module), func)(args), rest)


if __name__ == "__main__":
    sys.exit(main())
