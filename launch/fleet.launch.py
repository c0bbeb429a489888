"""Launch the simulated fleet on a full ROS 2 install (the `launch` and `launch_ros` packages):

    ros2 launch mapf_fleet fleet.launch.py
    ros2 launch mapf_fleet fleet.launch.py num_robots:=4 checkpoint:=/path/to/policy.pt
    ros2 launch mapf_fleet fleet.launch.py params_file:=/path/to/my_fleet.yaml

Starts the simulator (`mapf_simulator`) and one policy node per robot (`mapf_policy_<i>`, one
process each), every node with the shipped parameters file `config/fleet/fleet.yaml` (or
`params_file:=`). `num_robots` defaults to the simulator's `num_robots` in that file; the
checkpoint to `models/default.pt` of the package's share directory. Without ROS's launch tools,
`mapf-fleet up` starts the same fleet (and more layouts). test/test_launch_file.py keeps this file
honest: executables, parameters and files it names exist in the package.
"""

import os

import yaml
from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = "mapf_fleet"
PARAMS_FILE = os.path.join("config", "fleet", "fleet.yaml")
DEFAULT_CHECKPOINT = os.path.join("models", "default.pt")
SIMULATOR_NAME = "mapf_simulator"  # the simulator's section of the parameters file


def _robots_in(params_file: str) -> int:
    """The simulator's num_robots in the parameters file (8, the node's default, if unset)."""
    with open(params_file, encoding="utf-8") as handle:
        params = yaml.safe_load(handle) or {}
    section = params.get(SIMULATOR_NAME, {}).get("ros__parameters", {})
    return int(section.get("num_robots", 8))


def _fleet(context):
    share = get_package_share_directory(PACKAGE)
    params_file = LaunchConfiguration("params_file").perform(context) or os.path.join(share, PARAMS_FILE)
    checkpoint = LaunchConfiguration("checkpoint").perform(context) or os.path.join(share, DEFAULT_CHECKPOINT)
    robots_text = LaunchConfiguration("num_robots").perform(context)
    num_robots = int(robots_text) if robots_text else _robots_in(params_file)
    if num_robots < 1:
        raise ValueError(f"num_robots must be >= 1, got {num_robots}")
    simulator = Node(package=PACKAGE, executable="simulator", name=SIMULATOR_NAME, output="screen",
                     parameters=[params_file, {"num_robots": num_robots}])
    policies = [
        Node(package=PACKAGE, executable="policy", name=f"mapf_policy_{i}", output="screen",
             parameters=[params_file, {"robot_id": i, "checkpoint": checkpoint}])
        for i in range(num_robots)
    ]
    return [simulator, *policies]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument("num_robots", default_value="",
                              description="robots (default: num_robots of the parameters file)"),
        DeclareLaunchArgument("checkpoint", default_value="",
                              description="policy checkpoint (default: the package's models/default.pt)"),
        DeclareLaunchArgument("params_file", default_value="",
                              description="ROS parameters YAML (default: the package's config/fleet/fleet.yaml)"),
        OpaqueFunction(function=_fleet),
    ])
