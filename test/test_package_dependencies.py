"""package.xml declares every runtime dependency: each library that a module of the package (or
its launch file) imports, lazily or not, is an exec_depend by its rosdep key, or is named in the
package.xml comment of libraries without a rosdep key."""

from __future__ import annotations

import ast
import importlib.metadata
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# distribution -> rosdep key (ros/rosdistro rosdep/python.yaml); None: no key exists, the library
# must be named in package.xml's "no rosdep key" comment. A new library: add it to package.xml and here.
ROSDEP_KEYS = {
    "numpy": "python3-numpy", "PyYAML": "python3-yaml", "scipy": "python3-scipy", "numba": "python3-numba", "torch": "python3-torch",
    "tqdm": "python3-tqdm", "matplotlib": "python3-matplotlib", "ImageIO": "python3-imageio",
    "tensorboard": "python3-tensorboard-pip", "rosbags": "python3-rosbags-pip", "ray": None, "pymapf": None,
    "foxglove-sdk": None, "cmaes": None,
}
# optional extras, imported only to say they are missing (render: MP4 needs imageio-ffmpeg)
OPTIONAL = {"imageio_ffmpeg",
            # the POGEMA benchmark's, installed apart (<venv>/pogema, requirements-pogema.txt)
            "pogema"}
# imported only on a full ROS install (not installed here): ROS packages by their own names
ROS_ONLY = {"launch", "launch_ros"}


def _imports() -> dict[str, set[str]]:
    """Top-level module -> files importing it, over mapf_fleet/ and launch/ (stdlib left out)."""
    found: dict[str, set[str]] = {}
    for path in sorted([*(REPO / "mapf_fleet").rglob("*.py"), *(REPO / "launch").rglob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top != "mapf_fleet":
                    found.setdefault(top, set()).add(str(path.relative_to(REPO)))
    return found


def _package_xml() -> tuple[set[str], set[str]]:
    text = (REPO / "package.xml").read_text()
    depends = {e.text.strip() for e in ET.fromstring(text).iter() if e.tag in ("exec_depend", "depend")}
    keyless = set()
    for comment in re.findall(r"<!--(.*?)-->", text, re.S):
        match = re.search(r"no rosdep key:\s*([^(]*)", comment)
        if match:
            keyless |= {name.strip() for name in match.group(1).split(",") if name.strip()}
    return depends, keyless


def test_every_imported_library_is_declared():
    depends, keyless = _package_xml()
    distributions = importlib.metadata.packages_distributions()
    problems = []
    for module, files in sorted(_imports().items()):
        where = f"{module} (imported by {', '.join(sorted(files)[:2])})"
        dists = distributions.get(module, [])
        if module in depends or module in OPTIONAL:  # a ROS package (rclpy, nav_msgs, ...)
            continue
        if module in ROS_ONLY or any(d.startswith("ros-") for d in dists):
            problems.append(f"{where}: ROS package, no <exec_depend>{module}</exec_depend>")
            continue
        if not dists:
            problems.append(f"{where}: not installed, cannot tell its distribution")
            continue
        dist = dists[0]
        if dist not in ROSDEP_KEYS:
            problems.append(f"{where}: distribution {dist!r} is not in package.xml (nor in ROSDEP_KEYS)")
        elif ROSDEP_KEYS[dist] is None:
            if dist not in keyless:
                problems.append(f"{where}: {dist} has no rosdep key and is not in the 'no rosdep key' comment")
        elif ROSDEP_KEYS[dist] not in depends:
            problems.append(f"{where}: no <exec_depend>{ROSDEP_KEYS[dist]}</exec_depend>")
    assert not problems, "\n".join(problems)


def test_declared_python_libraries_are_pinned_requirements():
    """Each rosdep-declared library (and each keyless one) is in requirements.txt, so the venv
    install and a rosdep install get the same libraries."""
    depends, keyless = _package_xml()
    pinned = {re.split(r"[=<>~ ]", line)[0].strip().lower()
              for line in (REPO / "requirements.txt").read_text().splitlines()
              if line.strip() and not line.startswith("#")}
    for dist, key in ROSDEP_KEYS.items():
        if key in depends or dist in keyless:
            assert dist.lower() in pinned, f"{dist} is declared in package.xml but not pinned in requirements.txt"
    assert keyless, "package.xml lost its 'no rosdep key' comment"


def test_readme_colcon_section_is_consistent():
    """The README's full-ROS commands: colcon's base paths hold the two packages, the launch file
    exists, the pip line pins what requirements.txt pins, and every rosdep-keyless library is on it."""
    readme = (REPO / "README.md").read_text()
    section = readme[readme.index("## On a full ROS 2 Jazzy install (colcon)"):]
    build = re.search(r"colcon build --base-paths ([^\n]+)", section)
    assert build, "no colcon build command"
    names = {ET.parse(REPO / p / "package.xml").getroot().findtext("name") for p in build.group(1).split()}
    assert names == {"mapf_fleet", "mapf_fleet_interfaces"}
    rosdep = re.search(r"rosdep install --from-paths ([^-\n]+)--ignore-src", section)
    assert rosdep and set(rosdep.group(1).split()) == set(build.group(1).split())
    launch = re.search(r"ros2 launch mapf_fleet (\S+)", section)
    assert launch and (REPO / "launch" / launch.group(1)).is_file()
    pip = re.search(r"pip install ([^\n#]+)", section)
    requirements = (REPO / "requirements.txt").read_text().split()
    assert pip and all(pin in requirements for pin in pip.group(1).split()), pip
    _, keyless = _package_xml()
    assert {pin.split("==")[0] for pin in pip.group(1).split()} == keyless
