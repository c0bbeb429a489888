"""The packaging: both package.xml files are valid ROS packages, setup.py declares the entry
points and data files ament_python needs (and they resolve where the modules exist), the
generated interfaces import and survive rclpy serialization, the environment file and the pinned
requirements are consistent, and a message crosses a process boundary over ROS."""

from __future__ import annotations

import importlib
import importlib.util
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from setup_info import console_scripts, setup_kwargs

REPO = Path(__file__).resolve().parent.parent
INTERFACES = REPO / "mapf_fleet_interfaces"
REBUILD_HINT = "run `bash scripts/setup.sh` to rebuild mapf_fleet_interfaces into the venv"

# ---------------------------------------------------------------------------------------------
# package.xml


def _parse_package(path: Path):
    catkin_pkg_package = pytest.importorskip("catkin_pkg.package")
    package = catkin_pkg_package.parse_package(str(path))
    package.validate()  # raises InvalidPackage, e.g. on a malformed maintainer e-mail
    return package


def test_package_xml_is_a_valid_ament_python_package():
    package = _parse_package(REPO / "package.xml")
    assert package.name == "mapf_fleet"
    assert package.package_format == 3
    assert package.get_build_type() == "ament_python"
    exec_depends = {dep.name for dep in package.exec_depends}
    required = {
        "rclpy", "std_msgs", "geometry_msgs", "nav_msgs", "visualization_msgs",
        "mapf_fleet_interfaces", "python3-numpy", "python3-yaml",
    }
    assert required <= exec_depends, f"missing exec_depend: {sorted(required - exec_depends)}"
    assert any("torch" in name for name in exec_depends), "no exec_depend on pytorch"


def test_package_validation_rejects_a_bad_maintainer_email(tmp_path):
    # The validity checks above mean something only if catkin_pkg is strict about this.
    catkin_pkg_package = pytest.importorskip("catkin_pkg.package")
    bad = tmp_path / "package.xml"
    bad.write_text((REPO / "package.xml").read_text().replace("mapf-fleet@example.com", "nobody"))
    with pytest.raises(catkin_pkg_package.InvalidPackage):
        _parse_package(bad)


def test_interfaces_package_xml_is_a_valid_rosidl_package():
    package = _parse_package(INTERFACES / "package.xml")
    assert package.name == "mapf_fleet_interfaces"
    assert package.package_format == 3
    assert package.get_build_type() == "ament_cmake"
    assert "rosidl_interface_packages" in {group.name for group in package.member_of_groups}
    buildtool = {dep.name for dep in package.buildtool_depends}
    assert {"ament_cmake", "rosidl_default_generators"} <= buildtool


def test_package_versions_agree():
    package = _parse_package(REPO / "package.xml")
    assert setup_kwargs()["version"] == package.version


def test_interfaces_cmakelists_globs_msg_and_srv():
    # Adding a .msg/.srv must need no CMakeLists edit (the ROS engineer relies on it).
    text = (INTERFACES / "CMakeLists.txt").read_text()
    assert re.search(r"file\(GLOB[^)]*msg/\*\.msg", text), "msg/*.msg is not globbed"
    assert re.search(r"file\(GLOB[^)]*srv/\*\.srv", text), "srv/*.srv is not globbed"


# ---------------------------------------------------------------------------------------------
# setup.py (test/setup_info.py)


def test_setup_declares_cli_and_node_entry_points():
    assert console_scripts() == {
        "mapf-fleet": "mapf_fleet.cli:main",
        "simulator": "mapf_fleet.ros.simulator_node:main",
        "policy": "mapf_fleet.ros.policy_node:main",
        "aggregator": "mapf_fleet.ros.aggregator_node:main",
    }


@pytest.mark.parametrize(
    "name", ["mapf-fleet", "simulator", "policy", "aggregator"]
)
def test_entry_point_resolves_to_a_callable(name):
    module_name, func_name = console_scripts()[name].split(":")
    if importlib.util.find_spec(module_name) is None:
        pytest.skip(f"{module_name} is not written yet")
    module = importlib.import_module(module_name)
    assert callable(getattr(module, func_name, None)), f"{module_name} has no callable {func_name}"


def test_setup_installs_ament_index_marker_and_package_xml():
    data_files = dict(setup_kwargs()["data_files"])
    assert data_files["share/ament_index/resource_index/packages"] == ["resource/mapf_fleet"]
    assert (REPO / "resource" / "mapf_fleet").is_file()
    assert data_files["share/mapf_fleet"] == ["package.xml"]
    # every shipped config file is installed, at its own relative path
    config_files = sorted(
        str(p.relative_to(REPO)) for p in (REPO / "config").rglob("*")
        if p.is_file() and "__pycache__" not in p.parts
    )
    installed = sorted(
        f for target, files in data_files.items() if target.startswith("share/mapf_fleet/config")
        for f in files
    )
    assert installed == config_files
    for target, files in data_files.items():
        for f in files:
            if target.startswith("share/mapf_fleet/"):
                assert target == str(Path("share/mapf_fleet") / Path(f).parent)


def test_setup_cfg_puts_scripts_where_ros2_run_looks():
    text = (REPO / "setup.cfg").read_text()
    assert "script_dir=$base/lib/mapf_fleet" in text.replace(" ", "")
    assert "install_scripts=$base/lib/mapf_fleet" in text.replace(" ", "")


# ---------------------------------------------------------------------------------------------
# generated interfaces

# A sample value for each primitive ROS type, different from the default so a lost field shows.
_SAMPLES = {
    "boolean": True, "byte": b"\x07", "char": 7, "octet": b"\x07",
    "float": 0.5, "double": -2.25,
    "int8": -3, "uint8": 3, "int16": -300, "uint16": 300,
    "int32": -70000, "uint32": 70000, "int64": -(2**40), "uint64": 2**40,
    "string": "robot_7", "wstring": "robot_7",
}


def _sample_value(field_type: str):
    """A non-default value for a field type string from get_fields_and_field_types(), or None
    for nested messages (left at their defaults)."""
    sequence = re.fullmatch(r"sequence<([\w/]+)(?:, \d+)?>", field_type)
    if sequence:
        element = _sample_value(sequence.group(1))
        return None if element is None else [element, element]
    array = re.fullmatch(r"([\w/]+)\[(\d+)\]", field_type)
    if array:
        element = _sample_value(array.group(1))
        return None if element is None else [element] * int(array.group(2))
    bounded = re.fullmatch(r"(w?string)<\d+>", field_type)
    if bounded:
        return "r"
    return _SAMPLES.get(field_type)


def _interface_names(kind: str) -> list[str]:
    return sorted(p.stem for p in (INTERFACES / kind).glob(f"*.{kind}"))


def _filled(message_class):
    message = message_class()
    for name, field_type in message_class.get_fields_and_field_types().items():
        value = _sample_value(field_type)
        if value is not None:
            setattr(message, name, value)
    return message


def _assert_round_trip(message_class):
    serialization = pytest.importorskip("rclpy.serialization")
    message = _filled(message_class)
    data = serialization.serialize_message(message)
    assert isinstance(data, bytes) and len(data) > 0
    restored = serialization.deserialize_message(data, message_class)
    assert restored == message


def test_interfaces_package_has_messages_and_a_service():
    assert _interface_names("msg"), "mapf_fleet_interfaces/msg has no .msg file"
    assert _interface_names("srv"), "mapf_fleet_interfaces/srv has no .srv file"
    assert "FleetState" in _interface_names("msg")


@pytest.mark.parametrize("name", _interface_names("msg"))
def test_message_is_built_and_round_trips(name):
    msg_module = pytest.importorskip("mapf_fleet_interfaces.msg", reason=REBUILD_HINT)
    message_class = getattr(msg_module, name, None)
    assert message_class is not None, f"msg/{name}.msg is not in the built package: {REBUILD_HINT}"
    _assert_round_trip(message_class)


@pytest.mark.parametrize("name", _interface_names("srv"))
def test_service_is_built_and_round_trips(name):
    srv_module = pytest.importorskip("mapf_fleet_interfaces.srv", reason=REBUILD_HINT)
    service_class = getattr(srv_module, name, None)
    assert service_class is not None, f"srv/{name}.srv is not in the built package: {REBUILD_HINT}"
    _assert_round_trip(service_class.Request)
    _assert_round_trip(service_class.Response)


def test_sample_values_change_a_fleet_state():
    # Guards the round-trip tests against passing vacuously on all-default messages.
    msg_module = pytest.importorskip("mapf_fleet_interfaces.msg", reason=REBUILD_HINT)
    assert _filled(msg_module.FleetState) != msg_module.FleetState()


# ---------------------------------------------------------------------------------------------
# environment file and pins


def _sourced_env() -> dict[str, str]:
    out = subprocess.run(
        ["bash", "-c", f"source {REPO / 'scripts' / 'env.sh'} && env -0"],
        check=True, capture_output=True, env={"PATH": "/usr/bin:/bin", "HOME": "/tmp"},
    ).stdout.decode()
    return dict(item.split("=", 1) for item in out.split("\0") if "=" in item)


def test_env_file_makes_the_venv_a_loopback_ros_prefix():
    env = _sourced_env()
    venv = env["MAPF_FLEET_VENV"]
    assert env["AMENT_PREFIX_PATH"] == venv
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert env["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp"
    assert env["_ROS_WHEELS_BOOTSTRAP_COMPLETE"] == "1"
    ld_path = env["LD_LIBRARY_PATH"].split(":")
    assert ld_path[0] == f"{venv}/lib"
    assert env["PATH"].split(":")[0] == f"{venv}/bin"


def _pins(path: Path) -> dict[str, str]:
    pins = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            match = re.fullmatch(r"([A-Za-z0-9_.\-]+)==([\w.+]+)", line)
            assert match, f"{path.name}: {line!r} is not pinned as NAME==VERSION"
            pins[re.sub(r"[-_.]+", "-", match.group(1)).lower()] = match.group(2)
    return pins


def test_requirements_are_pinned_and_agree_with_constraints():
    requirements = _pins(REPO / "requirements.txt")
    constraints = _pins(REPO / "constraints.txt")
    for required in ("ros-jazzy-rclpy", "ros-jazzy-rmw-fastrtps-cpp", "torch", "numpy"):
        assert required in requirements
    assert requirements["torch"] == "2.13.0"
    for name, version in requirements.items():
        if name in constraints:
            assert constraints[name] == version, f"{name}: requirements {version}, constraints {constraints[name]}"


def test_ci_runs_the_readme_test_command():
    readme = (REPO / "README.md").read_text()
    assert "bash scripts/run.sh main" in readme
    assert "bash scripts/run.sh test" in readme
    assert "scripts/run.sh test" in (REPO / ".ci" / "run").read_text()


# ---------------------------------------------------------------------------------------------
# a message across processes


_PUBLISHER = """
import sys, time
import rclpy
from mapf_fleet_interfaces.msg import FleetState
rclpy.init()
node = rclpy.create_node("package_test_publisher")
pub = node.create_publisher(FleetState, "package_test/state", 10)
msg = FleetState(tick=41, rows=[1, 2, 3], cols=[4, 5, 6])
deadline = time.monotonic() + float(sys.argv[1])
while time.monotonic() < deadline:
    msg.tick += 1
    pub.publish(msg)
    time.sleep(0.05)
node.destroy_node()
rclpy.shutdown()
"""


@pytest.mark.ros
def test_fleet_state_crosses_processes(ros_env):
    rclpy = pytest.importorskip("rclpy")
    msg_module = pytest.importorskip("mapf_fleet_interfaces.msg", reason=REBUILD_HINT)
    publisher = subprocess.Popen(
        [sys.executable, "-c", _PUBLISHER, "15"], env=ros_env,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )
    context = rclpy.Context()
    rclpy.init(context=context)
    received = []
    try:
        node = rclpy.create_node("package_test_subscriber", context=context)
        node.create_subscription(
            msg_module.FleetState, "package_test/state", received.append, 10
        )
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)
        deadline = time.monotonic() + 15.0
        while not received and time.monotonic() < deadline and publisher.poll() is None:
            executor.spin_once(timeout_sec=0.1)
        executor.shutdown()
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
        publisher.kill()
        output = publisher.communicate(timeout=10)[0].decode(errors="replace")
    assert received, f"no FleetState from the publisher process (domain {ros_env.domain_id}):\n{output}"
    assert list(received[0].rows) == [1, 2, 3] and list(received[0].cols) == [4, 5, 6]
    assert received[0].tick > 41


# ---------------------------------------------------------------------------------------------
# the shared ROS test fixtures (test/conftest.py)


def _root_conftest():
    """test/conftest.py by path: `import conftest` may give test/ros/conftest.py instead."""
    spec = importlib.util.spec_from_file_location("mapf_fleet_root_conftest", REPO / "test" / "conftest.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_domain_reservations_are_exclusive_until_released():
    conftest = _root_conftest()

    first, first_fd = conftest._reserve_domain_id()
    second, second_fd = conftest._reserve_domain_id()
    try:
        assert first != second
        assert all(d in conftest.DOMAIN_IDS for d in (first, second))
    finally:
        os.close(first_fd)
        os.close(second_fd)


@pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="no /dev/shm")
def test_shm_cleanup_removes_only_unused_files():
    conftest = _root_conftest()

    tag = f"fastrtps_mapf_fleet_test_{os.getpid()}"
    held, stale = f"/dev/shm/{tag}_held", f"/dev/shm/{tag}_stale"
    old = time.time() - 3600  # older than the grace period for files being set up
    for path in (held, stale):
        with open(path, "w") as f:
            f.write("x")
        os.utime(path, (old, old))
    handle = open(held)
    try:
        conftest.cleanup_stale_fastdds_shm()
        assert os.path.exists(held), "a file a live process holds open was removed"
        assert not os.path.exists(stale), "an unused, old file was kept"
    finally:
        handle.close()
        for path in (held, stale):
            if os.path.exists(path):
                os.remove(path)
