"""`mapf-fleet param get|set|list NODE [NAME [VALUE]]`: read and change a running node's ROS
parameters, as `ros2 param` does on a full ROS install (which PyPI does not have).

    mapf-fleet param list mapf_simulator                 # every parameter with its value
    mapf-fleet param get mapf_simulator tick_period
    mapf-fleet param set mapf_simulator tick_period 0.5  # applied from the next tick
    mapf-fleet param get /fleet_a/mapf_policy_3 comm_timeout

NODE is the node's name (`mapf_simulator`, `mapf_aggregator`, `mapf_policy_<i>`), with its
namespace when the fleet has one (`/fleet_a/mapf_simulator`, or `--namespace /fleet_a`). VALUE
is read as YAML (`0.5`, `3`, `true`, `text`); an integer given for a floating-point parameter is
sent as a float. A node that refuses a change says why (the simulator applies `tick_period`,
`decision_timeout` and `progress_every` at runtime; policy nodes refuse every change): the reason
is printed and the exit code is 1. Exit 1 too when the node's parameter services do not answer
within `--timeout` seconds.
"""

from __future__ import annotations

import argparse
import sys

import yaml

from mapf_fleet.ros import common


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mapf-fleet param", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("verb", choices=("get", "set", "list"), help="what to do")
    parser.add_argument("node", help="node name, e.g. mapf_simulator or /fleet_a/mapf_policy_3")
    parser.add_argument("name", nargs="?", help="parameter name (get, set)")
    parser.add_argument("value", nargs="?", help="new value, as YAML (set)")
    parser.add_argument("--namespace", default="",
                        help="the fleet's namespace, for a NODE given without it")
    parser.add_argument("--timeout", type=float, default=10.0,
                        help="seconds to wait for the node's parameter services (default: 10)")
    return parser


def node_name(node: str, namespace: str = "") -> str:
    """The full name of NODE: '/fleet_a/mapf_simulator' kept; 'mapf_simulator' with namespace
    '/fleet_a' -> '/fleet_a/mapf_simulator', without one -> '/mapf_simulator'."""
    if node.startswith("/"):
        return node
    return common.in_namespace(node, namespace)


def parse_value(text: str):
    """VALUE as YAML (what `ros2 param set` accepts): 0.5 -> float, 3 -> int, true -> bool,
    [1, 2] -> list; anything else stays text."""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    return text if value is None or isinstance(value, dict) else value


def coerce(value, current):
    """An int for a floating-point parameter becomes a float (rcl refuses the type otherwise);
    `current` is the parameter's present value (None when unknown)."""
    if isinstance(current, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if (isinstance(current, list) and current and isinstance(current[0], float)
            and isinstance(value, list)):
        return [float(v) if isinstance(v, int) and not isinstance(v, bool) else v for v in value]
    return value


def _show(value) -> str:
    return yaml.safe_dump(value, default_flow_style=True, width=10**6).strip().removesuffix(
        "\n...").removesuffix(" ...") if not isinstance(value, str) else value


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    if args.verb in ("get", "set") and not args.name:
        print(f"mapf-fleet param {args.verb}: give the parameter NAME", file=sys.stderr)
        return 2
    if args.verb == "set" and args.value is None:
        print("mapf-fleet param set: give the new VALUE", file=sys.stderr)
        return 2
    if args.verb == "list" and args.name:
        print("mapf-fleet param list: takes only NODE", file=sys.stderr)
        return 2
    if not args.timeout > 0:
        print(f"mapf-fleet param: --timeout must be > 0, got {args.timeout}", file=sys.stderr)
        return 2
    common.prepare_environment()
    import rclpy

    target = node_name(args.node, args.namespace)
    rclpy.init(args=["mapf_fleet_param"])
    try:
        return ParamClient(target, args.timeout).run(args)
    finally:
        rclpy.try_shutdown()


class ParamClient:
    """A short-lived node with an rclpy AsyncParameterClient to the node `target`."""

    def __init__(self, target: str, timeout: float):
        from rclpy.node import Node
        from rclpy.parameter_client import AsyncParameterClient

        self.target = target
        self.timeout = timeout
        self.node = Node("mapf_fleet_param_client", start_parameter_services=False)
        self.client = AsyncParameterClient(self.node, target)

    def _wait(self, future):
        import rclpy

        rclpy.spin_until_future_complete(self.node, future, timeout_sec=self.timeout)
        if not future.done():
            raise TimeoutError(f"{self.target} did not answer within {self.timeout:g} s")
        return future.result()

    def _values(self, names: list[str]) -> list:
        from rclpy.parameter import parameter_value_to_python

        response = self._wait(self.client.get_parameters(names))
        return [parameter_value_to_python(v) for v in response.values]

    def run(self, args) -> int:
        try:
            if not self.client.wait_for_services(timeout_sec=self.timeout):
                print(f"mapf-fleet param: no parameter services of node {self.target} within "
                      f"{self.timeout:g} s (is it running, in this ROS_DOMAIN_ID and "
                      f"namespace? `mapf-fleet topics` lists what is there)", file=sys.stderr)
                return 1
            if args.verb == "list":
                names = sorted(self._wait(self.client.list_parameters()).result.names)
                for name, value in zip(names, self._values(names)):
                    print(f"{name}: {_show(value)}")
                return 0
            values = self._values([args.name])  # empty when the node has no such parameter
            current = values[0] if values else None
            if args.verb == "get":
                if current is None:
                    print(f"mapf-fleet param: {self.target} has no parameter {args.name!r}",
                          file=sys.stderr)
                    return 1
                print(_show(current))
                return 0
            return self._set(args.name, coerce(parse_value(args.value), current))
        except TimeoutError as exc:
            print(f"mapf-fleet param: {exc}", file=sys.stderr)
            return 1
        finally:
            self.node.destroy_node()

    def _set(self, name: str, value) -> int:
        from rclpy.parameter import Parameter

        try:
            parameter = Parameter(name, value=value)
        except TypeError as exc:
            print(f"mapf-fleet param set: {name}: cannot send {value!r} ({exc})",
                  file=sys.stderr)
            return 2
        result = self._wait(self.client.set_parameters([parameter])).results[0]
        if not result.successful:
            print(f"mapf-fleet param set: {self.target} refused {name} = {_show(value)}: "
                  f"{result.reason or 'no reason given'}", file=sys.stderr)
            return 1
        print(f"set {name} = {_show(value)} on {self.target}")
        return 0
