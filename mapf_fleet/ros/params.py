"""ROS parameter sources as rcl reads them (plain Python, no rclpy): which values a parameters
YAML file and the `-p` rules of a command line give a node, so `mapf-fleet up` can apply
"command line > params file > its own defaults" (issue 17 item 6) and knows the instance, the
record file and the checkpoint its nodes will really use.

rcl keeps one table of parameter overrides, filled in the order of the command line
(`--params-file F` and `-p name:=value` alike); a later value of a parameter replaces an earlier
one. `up` therefore passes a node `--params-file F`, then `-p` for its defaults that no file
sets, then `-p` for the options given on its command line, then the user's `--ros-args ...`.

Node keys of a params file: `/**` (every node), `name` or `/name` (root namespace),
`/ns/name`, `/**/name`, `*` for one name token; nested namespace mappings
(`ns: {name: {ros__parameters: ...}}`) are joined with `/`; nested parameter mappings are
joined with `.` (`a: {b: 1}` is parameter `a.b`).
"""

from __future__ import annotations

import re
from pathlib import Path

import yaml


def node_fqn(name: str, namespace: str = "/") -> str:
    namespace = "/" + namespace.strip("/") if namespace and namespace.strip("/") else ""
    return f"{namespace}/{name}"


def key_matches(key: str, fqn: str) -> bool:
    """Whether a params-file node key (`/**`, `/ns/name`, `/**/name`, `name*`) names `fqn`."""
    pattern = ""
    for token in key.strip("/").split("/"):
        if token == "**":
            pattern += r"(?:/[^/]+)*"
        else:
            pattern += "/" + re.escape(token).replace(r"\*", "[^/]*")
    return re.fullmatch(pattern or "/", fqn) is not None


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


def params_file_values(paths, fqn: str) -> dict:
    """The values the params files give node `fqn` (later files and entries win)."""
    values: dict = {}
    for path in paths:
        for key, params in read_params_file(path):
            if key_matches(key, fqn):
                values.update(params)
    return values


def ros_arg_rules(ros_args: list[str]) -> tuple[list[tuple[str, str, object]], list[str], str]:
    """From ROS arguments: the `-p [node:]name:=value` rules as (node, name, value), the
    `--params-file` paths and the `__ns` remapping ("" when none)."""
    rules, files, namespace = [], [], ""
    for i, arg in enumerate(ros_args[:-1]):
        value = ros_args[i + 1]
        if arg in ("-p", "--param") and ":=" in value:
            target, text = value.split(":=", 1)
            node, _, name = target.rpartition(":")
            try:
                parsed = yaml.safe_load(text) if text else ""
            except yaml.YAMLError:
                parsed = text
            rules.append((node, name, parsed))
        elif arg == "--params-file":
            files.append(value)
        elif arg in ("-r", "--remap") and value.startswith("__ns:="):
            namespace = value.split(":=", 1)[1]
    return rules, files, namespace


def command_line_values(rules, node_name: str) -> dict:
    """The `-p` rules that apply to a node named `node_name` (no node prefix, or its name)."""
    return {name: value for node, name, value in rules
            if not node or node.strip("/").split("/")[-1] == node_name}
