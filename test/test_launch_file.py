"""launch/fleet.launch.py (for full ROS installs, where `launch` and `launch_ros` exist; they are
not installed here) is read without importing launch: every executable it starts is a console
script of setup.py, every parameter it sets (in the launch file and in the shipped parameters
file it passes) is declared by that node, every file it names exists and is installed, every
launch argument it reads is declared."""

from __future__ import annotations

import ast
import importlib
import os
from pathlib import Path

import pytest
import yaml
from setup_info import console_scripts, setup_kwargs

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "fleet.launch.py"


def _console_scripts() -> dict[str, str]:
    """Console script name -> its module."""
    return {name: target.split(":")[0] for name, target in console_scripts().items()}


def _call_name(node: ast.Call) -> str:
    f = node.func
    return f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""


def _constants(tree: ast.AST) -> dict[str, object]:
    """Module-level NAME = <constant or os.path.join of constants>."""
    out = {}
    for stmt in tree.body:
        if isinstance(stmt, ast.Assign) and len(stmt.targets) == 1 and isinstance(stmt.targets[0], ast.Name):
            value = _value(stmt.value, out)
            if value is not None:
                out[stmt.targets[0].id] = value
    return out


def _value(node: ast.AST, names: dict):
    if isinstance(node, ast.Constant):
        return node.value
    if isinstance(node, ast.Name):
        return names.get(node.id)
    if isinstance(node, ast.Call) and _call_name(node) == "join":
        parts = [_value(a, names) for a in node.args]
        if all(isinstance(p, str) for p in parts):
            return os.path.join(*parts)
    return None


def _launch():
    tree = ast.parse(LAUNCH.read_text(), str(LAUNCH))
    names = _constants(tree)
    nodes = []
    for call in (n for n in ast.walk(tree) if isinstance(n, ast.Call) and _call_name(n) == "Node"):
        kw = {k.arg: k.value for k in call.keywords}
        params = set()
        for item in getattr(kw.get("parameters"), "elts", []):
            if isinstance(item, ast.Dict):
                params |= {_value(k, names) for k in item.keys}
        nodes.append({"package": _value(kw["package"], names), "executable": _value(kw["executable"], names),
                      "name": _value(kw["name"], names) if "name" in kw else None,
                      "name_node": kw.get("name"), "parameters": params})
    declared = {_value(c.args[0], names) for c in ast.walk(tree)
                if isinstance(c, ast.Call) and _call_name(c) == "DeclareLaunchArgument"}
    used = {_value(c.args[0], names) for c in ast.walk(tree)
            if isinstance(c, ast.Call) and _call_name(c) == "LaunchConfiguration"}
    return tree, names, nodes, declared, used


def _node_parameters(executable: str) -> set[str]:
    pytest.importorskip("rclpy")
    module = importlib.import_module(_console_scripts()[executable])
    return set(module.PARAMETERS)


def test_launch_file_starts_the_simulator_and_policy_nodes():
    _, _, nodes, _, _ = _launch()
    assert {n["executable"] for n in nodes} == {"simulator", "policy"}
    assert all(n["package"] == "mapf_fleet" for n in nodes)


def test_every_executable_is_a_console_script():
    scripts = _console_scripts()
    for node in _launch()[2]:
        assert node["executable"] in scripts, f"{LAUNCH.name}: executable {node['executable']!r} " \
                                              f"is not a console script of setup.py {sorted(scripts)}"


def test_every_parameter_set_is_declared_by_its_node():
    for node in _launch()[2]:
        declared = _node_parameters(node["executable"])
        assert None not in node["parameters"], f"{LAUNCH.name}: a parameter name that is not a constant"
        unknown = node["parameters"] - declared
        assert not unknown, f"{LAUNCH.name}: {node['executable']} does not declare {sorted(unknown)}"


def test_every_file_named_exists_and_is_installed():
    _, names, _, _, _ = _launch()
    files = {k: v for k, v in names.items() if isinstance(v, str) and os.sep in v}
    assert set(files) >= {"PARAMS_FILE", "DEFAULT_CHECKPOINT"}, files
    installed = {os.path.join(os.path.relpath(target, "share/mapf_fleet"), os.path.basename(f))
                 for target, sources in setup_kwargs()["data_files"] for f in sources
                 if target.startswith("share/mapf_fleet")}
    for name, path in files.items():
        assert (REPO / path).exists(), f"{LAUNCH.name}: {name} = {path!r} does not exist in the package"
        assert path in installed, f"{LAUNCH.name}: {name} = {path!r} is not installed by setup.py"
    assert "launch/fleet.launch.py" in installed  # where `ros2 launch mapf_fleet` looks


def test_shipped_parameters_file_matches_the_nodes():
    """The parameters the launch file passes through config/fleet/fleet.yaml: each node section
    sets only parameters that node declares; the simulator's section is the name it launches."""
    _, names, nodes, _, _ = _launch()
    params = yaml.safe_load((REPO / names["PARAMS_FILE"]).read_text())
    by_name = {"mapf_simulator": "simulator", "mapf_aggregator": "aggregator", "/**": "policy"}
    assert set(params) <= set(by_name), sorted(params)
    for section, executable in by_name.items():
        keys = set(params.get(section, {}).get("ros__parameters", {}))
        unknown = keys - _node_parameters(executable)
        assert not unknown, f"{names['PARAMS_FILE']}: {section} sets undeclared {sorted(unknown)}"
    simulator = next(n for n in nodes if n["executable"] == "simulator")
    assert simulator["name"] in params, f"simulator launched as {simulator['name']!r}: no section of its own"


def test_every_launch_argument_read_is_declared():
    _, _, _, declared, used = _launch()
    assert used and used <= declared, f"read but not declared: {sorted(used - declared)}"
