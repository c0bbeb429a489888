"""Layers point one way (docs/architecture.md, "Layers"):

    grid; coordination; fleet and models; training and ros; evaluation; view

A layer imports only layers of the levels below its own: never a layer above, never its
sibling on the same level (fleet <-> models, training <-> ros). On top of the order:
- grid, coordination and fleet are numpy only (no torch), and no layer but ros and the live
  view imports rclpy: training and evaluation never import ros either (ros is where rclpy is);
- evaluation never imports the Ape-X trainer (`training.trainer`, Ray);
- in view, only the live view (`view/live.py`, `mapf-fleet view`) imports ros; the renderer and
  the pictures read recorded runs without ROS.
The package's support modules (aliases, entry, files, paths, stop_signals, version) import no layer; cli.py
dispatches to all of them and is outside the order.

Checked statically on every import statement of the package (also the lazy ones inside
functions), so a layer cannot reach up even on a code path no other test runs."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mapf_fleet"

LEVELS = (("grid",), ("coordination",), ("fleet", "models"), ("training", "ros"),
          ("evaluation",), ("view",))
LAYERS = tuple(layer for level in LEVELS for layer in level)
# mapf_fleet/<name>.py, below every layer
SUPPORT = ("aliases", "entry", "files", "paths", "stop_signals", "version")
LEVEL_OF = {layer: k for k, level in enumerate(LEVELS) for layer in level}
NO_TORCH = ("grid", "coordination", "fleet")
NO_ROS = ("grid", "coordination", "fleet", "models", "training", "evaluation", "view")
ROS_ALLOWED_IN = {"view/live.py"}  # the live view subscribes to the fleet's topics
EXTRA = {"evaluation": ("mapf_fleet.training.trainer",)}


def forbidden(layer: str, relative: str) -> tuple[str, ...]:
    """Modules (prefixes) that file `relative` (e.g. "view/live.py") of `layer` must not
    import."""
    above = tuple(f"mapf_fleet.{other}" for other in LAYERS
                  if other != layer and LEVEL_OF[other] >= LEVEL_OF[layer])
    out = above + EXTRA.get(layer, ())
    if layer in NO_TORCH:
        out += ("torch",)
    if layer in NO_ROS and relative not in ROS_ALLOWED_IN:
        out += ("rclpy", "mapf_fleet.ros")
    return out


def imports_of(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), filename=str(path))
    package = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts[:-1])
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            found.append((node.lineno, module))
    return found


def _bad_imports(path: Path, rules) -> list[str]:
    return [f"{path.relative_to(PACKAGE.parent)}:{line} imports {module}"
            for line, module in imports_of(path)
            if any(module == f or module.startswith(f + ".") for f in rules)]


@pytest.mark.parametrize("layer", LAYERS)
def test_layer_imports_point_one_way(layer):
    bad = []
    for path in sorted((PACKAGE / layer).rglob("*.py")):
        bad += _bad_imports(path, forbidden(layer, path.relative_to(PACKAGE).as_posix()))
    assert not bad, "\n".join(bad)


def test_support_modules_import_no_layer():
    rules = tuple(f"mapf_fleet.{layer}" for layer in LAYERS) + ("torch", "rclpy")
    bad = [line for name in SUPPORT for line in _bad_imports(PACKAGE / f"{name}.py", rules)]
    assert not bad, "\n".join(bad)


def test_every_package_folder_is_a_layer():
    """A new folder needs its place in the order (and in docs/architecture.md)."""
    folders = {p.name for p in PACKAGE.iterdir()
               if p.is_dir() and (p / "__init__.py").exists()}
    modules = {p.stem for p in PACKAGE.glob("*.py")} - {"__init__", "cli"}
    assert folders == set(LAYERS)
    assert modules == set(SUPPORT)


def test_the_rules_forbid_what_the_order_says():
    """The rules themselves (a typo in LEVELS would otherwise pass everything)."""
    assert "mapf_fleet.ros" in forbidden("evaluation", "evaluation/runner.py")
    assert "mapf_fleet.ros" in forbidden("view", "view/replay.py")
    assert "mapf_fleet.ros" not in forbidden("view", "view/live.py")
    assert "mapf_fleet.fleet" in forbidden("models", "models/exchange.py")  # sibling
    assert "mapf_fleet.models" in forbidden("fleet", "fleet/run.py")  # sibling
    assert "mapf_fleet.ros" in forbidden("training", "training/actor.py")  # sibling
    assert "mapf_fleet.training" in forbidden("ros", "ros/hub.py")  # sibling
    assert "mapf_fleet.view" in forbidden("evaluation", "evaluation/render.py")
    assert "mapf_fleet.evaluation" in forbidden("ros", "ros/hub.py")
    assert "torch" in forbidden("fleet", "fleet/run.py")
    assert "mapf_fleet.models" not in forbidden("ros", "ros/hub.py")
    assert not any(f.startswith("mapf_fleet.") for f in forbidden("view", "view/live.py"))


def test_the_check_sees_lazy_and_relative_imports(tmp_path):
    module = PACKAGE / "grid" / "_layering_probe.py"
    assert not module.exists()
    source = "def f():\n    import torch\n    from ..ros import common\n"
    try:
        module.write_text(source)
        found = [name for _, name in imports_of(module)]
    finally:
        module.unlink()
    assert found == ["torch", "mapf_fleet.ros"]
