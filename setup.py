"""ament_python package mapf_fleet (also a plain setuptools package: `pip install -e .`)."""

from __future__ import annotations

import os
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "mapf_fleet"
HERE = os.path.dirname(os.path.abspath(__file__))


def tree_data_files(top: str) -> list[tuple[str, list[str]]]:
    """data_files entries installing every file under `top` to share/mapf_fleet/<top>/...,
    keeping sub-directories (config/fleet/*.yaml -> share/mapf_fleet/config/fleet/)."""
    entries: dict[str, list[str]] = {}
    for path in sorted(glob(os.path.join(top, "**", "*"), recursive=True)):
        if os.path.isfile(path) and "__pycache__" not in path:
            target = os.path.join("share", PACKAGE, os.path.dirname(path))
            entries.setdefault(target, []).append(path)
    return sorted(entries.items())


# Paths relative to setup.py, as colcon and pip both run it from here.
os.chdir(HERE)

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={"mapf_fleet.view": ["static/*"]},  # the page of `mapf-fleet view`
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        *tree_data_files("config"),
        *tree_data_files("models"),
        *tree_data_files("launch"),  # `ros2 launch mapf_fleet fleet.launch.py` on a full ROS install
    ],
    # Runtime Python dependencies are pinned in requirements.txt (ROS comes from the ROS
    # wheels or a full ROS install, which setuptools cannot express), so none are listed here.
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="mapf_fleet developers",
    maintainer_email="mapf-fleet@example.com",
    description="Learned multi-agent path finding (DHC, DCC) on a ROS 2 robot fleet",
    license="MIT",
    python_requires=">=3.11",
    entry_points={
        "console_scripts": [
            "mapf-fleet = mapf_fleet.cli:main",
            "simulator = mapf_fleet.ros.simulator_node:main",
            "policy = mapf_fleet.ros.policy_node:main",
            "aggregator = mapf_fleet.ros.aggregator_node:main",
        ],
    },
)
