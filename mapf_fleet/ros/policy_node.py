"""PolicyNode: one robot's learned policy as a ROS node: its parameters (robot_id, checkpoint,
device, guidance, timeouts, conflict_rule, ranking), its move and heartbeat publishers and, for
DCC, its request and reply services. `make_policy_nodes` builds the nodes of one process (every
entry point: `policy`, `mapf-fleet node policy --robots`, `up --single-process`).

The robots hosted in one process are driven by one `mapf_fleet.ros.hub.PolicyHub` (shared
subscriptions, batched inference, one peer message per process and round: DHC hidden vectors,
DCC announcements; DCC requests/replies to other processes as one DccBatch call per process
pair; see docs/architecture.md): `spin_policy_nodes` sets it up for one robot (`ros2 run
mapf_fleet policy`) or many (`mapf-fleet node policy --robots 0-7`).
Every peer message carries (episode, tick); a message of an older tick is stale and ignored. A
peer missing after `comm_timeout` is left out and reported in the move (missing_peers). A node
started mid-run joins at the newest tick it receives (with a fresh recurrent state).
A move carries the robot's five actions ranked (`ranking`); the node commands nothing:
the tick's arbiter (simulator or aggregator) publishes the waypoints.
"""

from __future__ import annotations

import sys
import time

import rclpy
from mapf_fleet_interfaces.srv import DccMessage
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from mapf_fleet.coordination.ranking import default_ranking
from mapf_fleet.entry import one_line_errors
from mapf_fleet.fleet import parameters
from mapf_fleet.ros import common

PARAMETERS = parameters.POLICY  # name -> Param (fleet.parameters: the one table)


def load_policy_model(path: str, device: str = "cpu"):
    """(model in eval mode on `device` (common.resolve_device), checkpoint metadata)."""
    import torch

    from mapf_fleet.models.checkpoint import load_checkpoint

    device = common.resolve_device(device)
    torch.set_num_threads(1)  # many robots share the cores: one thread each
    model, metadata = load_checkpoint(path)
    return model.to(device).eval(), metadata


class PolicyNode(Node):
    """One robot: its parameters, its publishers (move, heartbeat) and, for DCC, its request
    and reply services. The decisions are made by the process's
    `PolicyHub` (mapf_fleet.ros.hub), which batches the robots hosted in one process.
    `model` and `metadata`: a checkpoint already loaded (the robots of one process share the
    first node's); without `metadata` the checkpoint records no ranking."""

    def __init__(self, robot_id: int | None = None, checkpoint: str | None = None, model=None,
                 metadata=None, hosted: bool = False, **node_kwargs):
        overrides = list(node_kwargs.pop("parameter_overrides", None) or [])
        if robot_id is not None or checkpoint is not None:
            from rclpy.parameter import Parameter

            if robot_id is not None:
                overrides.append(Parameter("robot_id", value=int(robot_id)))
            if checkpoint is not None:
                overrides.append(Parameter("checkpoint", value=str(checkpoint)))
        name = f"mapf_policy_{robot_id}" if robot_id is not None else "mapf_policy"
        self.has_parameter_services = node_kwargs.get("start_parameter_services", True)
        super().__init__(name, parameter_overrides=overrides, **node_kwargs)
        for pname, param in PARAMETERS.items():
            self.declare_parameter(pname, param.default,
                                   ParameterDescriptor(description=param.description))
        for alias, pname in parameters.ALIASES.items():  # deprecated names still read
            self.declare_parameter(alias, "", ParameterDescriptor(
                description=f"deprecated: {pname}"))
        values = {pname: self.get_parameter(pname).value for pname in PARAMETERS}
        for alias, pname in parameters.ALIASES.items():
            old = self.get_parameter(alias).value
            if old not in ("", None):
                self.get_logger().warning(parameters.alias_warning(alias))
                if not values[pname]:
                    values[pname] = old
        values = parameters.check_values(PARAMETERS, values)  # before the checkpoint loads
        self.robot_id = values["robot_id"]
        self.comm_timeout = values["comm_timeout"]
        self.service_timeout = values["service_timeout"]
        self.status_period = values["status_period"]
        # one RobotMove / RobotStatus per robot instead of the process's batches (the hub)
        self.per_robot_messages = values["per_robot_messages"]
        self.episode_timeout = values["episode_timeout"]
        self.conflict_rule = values["conflict_rule"]
        # the guidance file (None: none) the robot's distances are to be read from
        self.guidance = parameters.resolve_guidance(values["guidance"])
        given = values["ranking"]
        if model is None:
            path = values["checkpoint"]
            if not path:
                raise ValueError("parameter 'checkpoint' is required (a checkpoint file path)")
            model, metadata = load_policy_model(path, values["device"])
        self.model = model
        self.checkpoint_metadata = metadata or {}
        # a ranking given (params file, -p, `up --ranking`) always wins; else the ranking the
        # checkpoint was trained behind under the rule (metadata rankings), else the ranking
        # measured best under the rule (docs/results.md, "Which ranking under which rule")
        self.ranking = given or default_ranking(self.conflict_rule,
                                               self.checkpoint_metadata.get("rankings"))
        self.algo = model.config.algo
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.hub = None  # set by PolicyHub
        # the moves and heartbeats of every robot of the process go out through its hub's two
        # publishers (one endpoint each per process, not per robot: DDS discovery grows with the
        # endpoints of every process), as do the peer messages (DHC vectors, DCC announcements)
        if self.algo == "dcc" and not hosted:
            # a robot alone in its process also takes DCC messages from senders that are not
            # hubs (hubs send each other one `DccBatch` per tick); hosted robots leave these
            # out (4 endpoints a robot)
            group = ReentrantCallbackGroup()
            self.create_service(DccMessage, common.rel(common.dcc_request_service(self.robot_id)),
                                self._on_dcc_request, callback_group=group)
            self.create_service(DccMessage, common.rel(common.dcc_reply_service(self.robot_id)),
                                self._on_dcc_reply, callback_group=group)
        self.has_robot_services = self.algo == "dcc" and not hosted

    def _on_set_parameters(self, parameters):
        """Policy node parameters are read once, when the node (and its process's hub) starts:
        a change at runtime would be accepted and read back without any effect, so it is
        refused with the reason (`ros2 param set` prints it)."""
        from rcl_interfaces.msg import SetParametersResult

        names = ", ".join(p.name for p in parameters)
        return SetParametersResult(
            successful=False,
            reason=f"{names}: read when the policy node starts; restart robot "
                   f"{self.robot_id}'s node with the new value (--ros-args -p NAME:=VALUE)")

    def _on_dcc_request(self, request, response):
        response.accepted = self.hub is not None and self.hub.deliver("request", self.robot_id,
                                                                      request)
        return response

    def _on_dcc_reply(self, request, response):
        response.accepted = self.hub is not None and self.hub.deliver("reply", self.robot_id,
                                                                      request)
        return response


def needs_spinning(node: PolicyNode) -> bool:
    """Whether the node itself serves anything besides its parameters: a DCC node its
    per-robot request and reply services (for senders that are not hubs; hubs send each other
    one `DccBatch` per tick). Every robot node is spun by a second executor, apart from the
    decision path (`spin_policy_nodes`)."""
    return node.has_robot_services


def host_kwargs(count: int) -> dict:
    """Node options when `count` robots share a process. Every robot keeps its parameter
    services (each robot's parameters can be read, and set, whatever the process layout); they
    are spun apart from the decision path (`spin_policy_nodes`). Robots hosted several per
    process leave out what the hub serves for them (`hosted`: the per-robot DCC services) and
    the type description service (its own `~/get_type_description`: the hub's node answers
    for the same message types): every endpoint is discovered by every process."""
    if count <= 1:
        return {}
    from rclpy.parameter import Parameter

    return {"hosted": True,
            "parameter_overrides": [Parameter("start_type_description_service", value=False)]}


def make_policy_nodes(robot_ids: list[int] | None = None, **node_kwargs) -> list[PolicyNode]:
    """The policy nodes of one process (the one way to build them): one per robot of
    `robot_ids` (None: one node whose robot_id comes from its parameters), with the options of
    `host_kwargs`; the first loads the checkpoint on its `device`, the others share its model
    (inference only, no state in it) and metadata. `node_kwargs`: rclpy Node options (e.g.
    context)."""
    if robot_ids is None:
        return [PolicyNode(**node_kwargs)]
    options = {**host_kwargs(len(robot_ids)), **node_kwargs}
    first = PolicyNode(robot_id=robot_ids[0], **options)
    return [first] + [PolicyNode(robot_id=i, model=first.model,
                                 metadata=first.checkpoint_metadata, **options)
                      for i in robot_ids[1:]]


def spin_policy_nodes(nodes: list[PolicyNode], until=None, extra_nodes=(), on_started=None,
                      signals=None, on_stop=None, side_nodes=()) -> int:
    """Spin policy nodes hosted in this process (one PolicyHub for all of them) plus
    `extra_nodes` (e.g. a simulator) until `until()` is true, a stop signal (`signals`, a
    `processes.StopSignals`) or a failed callback (logged by `SpinThread`). With `on_stop` (e.g.
    stop the simulator's run), a signal or failure calls it once and the loop goes on until
    `until()` (a second signal: at once). One single-threaded executor: the callbacks only store
    and notify (the hub thread computes), and a thread pool costs more than it saves under the
    GIL. Returns the process's exit code: 0, 128 + the signal (130 / 143), or 1 after a failed
    callback."""
    from mapf_fleet.ros.hub import PolicyHub

    hub = PolicyHub(nodes, nodes[0].model)
    # The decision path's executor holds only the hub's node (and `extra_nodes`): the Python
    # executor rebuilds its wait set from every entity it holds on every spin, so 32 robot nodes
    # with 6 parameter services and 2 DCC services each made every message cost milliseconds.
    executor = SingleThreadedExecutor()
    for node in list(extra_nodes) + [hub.node]:
        executor.add_node(node)
    spinner = common.SpinThread(executor).start()
    # the robots' own nodes (parameter services; DCC: the per-robot services): their own
    # executor and thread, off the decision path
    # (and `side_nodes`: e.g. the simulator's goal inputs, `ros.goals`)
    parameter_nodes = [n for n in nodes if needs_spinning(n) or n.has_parameter_services]
    parameter_nodes += list(side_nodes)
    parameter_spinner = None
    if parameter_nodes:
        parameter_executor = SingleThreadedExecutor()
        for node in parameter_nodes:
            parameter_executor.add_node(node)
        parameter_spinner = common.SpinThread(parameter_executor).start()
    hub.start()
    if on_started is not None:
        on_started()
    code, stopping = 0, False
    try:
        while rclpy.ok() and not (until and until()):
            failed = any(s is not None and s.error is not None
                         for s in (spinner, parameter_spinner))
            signalled = signals is not None and signals.requested
            if failed or signalled:
                code = signals.exit_code if signalled else 1
                if on_stop is None or (signalled and signals.forced):
                    break
                if not stopping:
                    stopping = True
                    on_stop()
            time.sleep(0.05)
    except KeyboardInterrupt:
        code = 130
    finally:
        hub.stop()
        spinner.stop()
        if parameter_spinner is not None:
            parameter_spinner.stop()
        for node in list(extra_nodes) + list(side_nodes) + hub.all_nodes:
            node.destroy_node()
    return code


@one_line_errors("policy")
def main(argv: list[str] | None = None) -> int:
    common.prepare_environment()
    args = sys.argv if argv is None else ["policy"] + list(argv)
    signals = common.init_process(args)
    try:
        return spin_policy_nodes(make_policy_nodes(), signals=signals)
    finally:
        rclpy.try_shutdown()
        signals.restore()


if __name__ == "__main__":
    sys.exit(main())
