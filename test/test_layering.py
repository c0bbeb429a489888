"""Layers point one way: grid <- coordination <- fleet <- models <- training, evaluation <- ros.

Checked statically on every import statement of the package (also the lazy ones inside
functions), so a layer cannot reach up even on a code path no other test runs."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mapf_fleet"

# layer -> modules it must never import (prefix match)
FORBIDDEN = {
    "grid": ("torch", "rclpy", "mapf_fleet.models", "mapf_fleet.coordination", "mapf_fleet.training",
             "mapf_fleet.evaluation", "mapf_fleet.ros", "mapf_fleet.fleet"),
    "coordination": ("torch", "rclpy", "mapf_fleet.models", "mapf_fleet.training",
                     "mapf_fleet.evaluation", "mapf_fleet.ros", "mapf_fleet.fleet"),
    # the fleet core (a run's ticks, goals, tasks, arbiter, record): numpy only, shared by the
    # simulator, the real-robot aggregator and the evaluator's lifelong rollout
    "fleet": ("torch", "rclpy", "mapf_fleet.models", "mapf_fleet.training",
              "mapf_fleet.evaluation", "mapf_fleet.ros"),
    "models": ("rclpy", "mapf_fleet.training", "mapf_fleet.evaluation", "mapf_fleet.ros"),
    "training": ("rclpy", "mapf_fleet.evaluation", "mapf_fleet.ros"),
    "evaluation": ("rclpy", "mapf_fleet.training.trainer", "mapf_fleet.ros"),
}


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


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_layer_imports_point_one_way(layer):
    bad = []
    for path in sorted((PACKAGE / layer).rglob("*.py")):
        for line, module in imports_of(path):
            if any(module == f or module.startswith(f + ".") for f in FORBIDDEN[layer]):
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line} imports {module}")
    assert not bad, "\n".join(bad)


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
