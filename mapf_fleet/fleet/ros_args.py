"""The user's `--ros-args ...` as `mapf-fleet up` reads them (plain Python): `-p [node:]name:=value`
rules, `--params-file` files, the namespace remapping and the logging arguments passed on."""

from __future__ import annotations

from dataclasses import dataclass

import yaml


def parse_rule(text: str) -> tuple[str, str, object]:
    """`-p [node:]name:=value` -> (node, name, value as YAML); ValueError when malformed."""
    if ":=" not in text:
        raise ValueError(f"-p {text}: expected name:=value")
    target, raw = text.split(":=", 1)
    node, _, name = target.rpartition(":")
    try:
        value = yaml.safe_load(raw) if raw else ""
    except yaml.YAMLError:
        value = raw
    return node, name, value


# ROS arguments `up` passes on unchanged (after --ros-args), with how many values each takes
PASSED_ROS_ARGS = {"--log-level": 1, "--log-config-file": 1, "--enclave": 1, "-e": 1,
                   "--disable-rosout-logs": 0, "--enable-rosout-logs": 0,
                   "--disable-stdout-logs": 0, "--enable-stdout-logs": 0,
                   "--disable-external-lib-logs": 0, "--enable-external-lib-logs": 0,
                   "--log-file-name": 1}


@dataclass
class RosArgs:
    """The user's `--ros-args ...` as `up` reads them: the parameter sources in order
    (("file", path) / ("rule", node, name, value, text)), the namespace remapping and the
    arguments passed on as they are."""
    sources: list
    namespace: str
    passed: list


def read_ros_args(ros_args: list[str], is_up_option=lambda a: False) -> RosArgs:
    """ValueError with one line for an argument `up` does not know (an `up` option put after
    --ros-args, a typo)."""
    sources, namespace, passed = [], "", []
    args = [a for a in ros_args if a != "--ros-args"]
    i = 0
    while i < len(args):
        arg = args[i]
        value = args[i + 1] if i + 1 < len(args) else None
        if arg == "--":
            i += 1
            continue
        if arg in ("-p", "--param", "--params-file", "-r", "--remap") and value is None:
            raise ValueError(f"--ros-args {arg}: needs a value")
        if arg in ("-p", "--param"):
            node, name, parsed = parse_rule(value)
            sources.append(("rule", node, name, parsed, value))
        elif arg == "--params-file":
            sources.append(("file", value))
        elif arg in ("-r", "--remap"):
            if value.startswith("__ns:="):
                namespace = value.split(":=", 1)[1]
            elif value.startswith("__node:=") or value.startswith("__name:="):
                raise ValueError(f"--ros-args {arg} {value}: the fleet's node names are fixed "
                                 f"(mapf_simulator, mapf_policy_<i>, ...)")
            else:
                passed += [arg, value]
        elif arg in PASSED_ROS_ARGS:
            passed += args[i:i + 1 + PASSED_ROS_ARGS[arg]]
            i += PASSED_ROS_ARGS[arg]
        elif is_up_option(arg):
            raise ValueError(f"{arg} is an option of `mapf-fleet up`: put it before --ros-args "
                             f"(everything after --ros-args goes to the ROS nodes)")
        else:
            raise ValueError(f"--ros-args: unknown ROS argument {arg!r}")
        i += 1 + (arg in ("-p", "--param", "--params-file", "-r", "--remap"))
    return RosArgs(sources, namespace, passed)
