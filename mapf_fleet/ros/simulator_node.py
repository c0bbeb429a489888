"""SimulatorNode: the grid world as a ROS node, stepping the fleet in lockstep ticks.

Tick k: publish the fleet state of k (and poses, markers); wait for every robot's move for k (a
move missing after `decision_timeout` counts as "stay" and is reported, and the robot cannot be
pushed); arbitrate the moves with `conflict_rule` (`arbiter.TickArbiter`: "pibt" = PIBT over the
robots' ranked actions, "pibt_anchor" (default) = the same with the top-priority robot on its
distance order, "revert" = the paper's grid.resolve_moves on their first choices);
command each robot's waypoint; publish progress; go on with k + 1. The state's `last_actions`
are the executed actions under "pibt" / "pibt_anchor" (DCC's last-action input, as the evaluator's shield) and
the robots' first choices under "revert" (as the paper's environment). At the end the outcome
(success, steps, collisions, missed decisions) is published (latched) and optionally written to
`record_file` as JSON with the whole trajectory. The tick bookkeeping it shares with the
aggregator is in `lockstep` (plain Python) and `fleet_io` (topics, loop, main).
"""

from __future__ import annotations

import random
import sys
import threading

import numpy as np
from geometry_msgs.msg import PoseStamped
from mapf_fleet_interfaces.msg import FleetOutcome
from rclpy.node import Node

from mapf_fleet.entry import one_line_errors
from mapf_fleet.ros import common, fleet_io
from mapf_fleet.fleet.arbiter import TickArbiter, check_conflict_rule
from mapf_fleet.ros.lockstep import (INSTANCE_PARAMETERS, RUN_PARAMETERS, Decisions, FleetTicker,
                                     RunRecorder, instance_source, require_positive,
                                     set_parameters_result)

PARAMETERS = {
    # name: (default, description)
    **INSTANCE_PARAMETERS,
    **RUN_PARAMETERS,
    "tick_period": (0.0, "minimum seconds per tick (0: as fast as the robots decide)"),
    "start_tick": (0, "first tick number (a restarted simulator may continue a count)"),
}


class SimulatorNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__("mapf_simulator", **node_kwargs)
        p = self.params = fleet_io.declare_parameters(self, PARAMETERS)
        self.instance = instance_source(p).load()
        require_positive(p, ["decision_timeout"])
        self.geometry = common.MapGeometry(float(p["resolution"]))
        self.num_robots = self.instance.num_agents
        self.episode = random.getrandbits(63)
        self.positions = np.array(self.instance.starts, dtype=np.int64)
        self.goals = np.array(self.instance.goals, dtype=np.int64)
        # -1: no action yet (MAPFEnv.last_actions; DCC feeds a zero one-hot then)
        self.last_actions = np.full(self.num_robots, -1, dtype=np.int64)
        self.outcome: FleetOutcome | None = None
        self.finished = threading.Event()

        self.conflict_rule = check_conflict_rule(str(p["conflict_rule"]))
        self.arbiter = TickArbiter(self.instance.grid, self.goals, self.conflict_rule)
        self.ticker = FleetTicker(self.num_robots, self.episode, int(p["start_tick"]))
        # who talked to whom: per robot its partners (DHC) / requested peers (DCC), and the
        # peer messages it used
        self.recorder = RunRecorder(self.episode, self.num_robots, self.goals,
                                    int(p["max_steps"]),
                                    series=("collided", "requested", "messages",
                                            "executed", "overridden"),
                                    conflict_rule=self.conflict_rule)
        self.channels = fleet_io.FleetChannels(self, self.ticker, self.geometry)
        quiet = common.quiet_publisher_events()  # per-robot publishers: keep the wait set small
        self.pose_pubs = [self.create_publisher(PoseStamped, common.rel(common.pose_topic(i)),
                                                common.reliable_qos(10), event_callbacks=quiet)
                          for i in range(self.num_robots)]
        self.channels.publish_map_and_goals(self.instance.grid, self.goals)
        self.get_logger().info(
            f"instance {self.instance.size[0]}x{self.instance.size[1]} with {self.num_robots} "
            f"robots, conflict rule {self.conflict_rule}, episode {self.episode}")
        # tick_period, decision_timeout, progress_every apply from the next tick; changing any
        # other parameter at runtime is refused with the reason (lockstep.RUNTIME_PARAMETERS)
        self.add_on_set_parameters_callback(
            lambda parameters: set_parameters_result(self.params, parameters, self.get_logger()))
        self._thread = threading.Thread(
            target=fleet_io.run_reporting_failure, args=(self, "simulator", self._run),
            name="simulator", daemon=True)

    @property
    def tick(self) -> int:
        return self.ticker.tick

    def start(self):
        self._thread.start()

    # ---- the lockstep loop (own thread) ----
    def _run(self):
        subscribers = int(self.params["state_subscribers"])
        missing = self.ticker.wait_ready(float(self.params["startup_timeout"]),
                                         also=lambda: self.channels.state_heard(subscribers))
        if self.ticker.stopped:
            self.get_logger().info(f"stopped while waiting for robots {missing}")
        elif missing:
            self.get_logger().warning(f"starting without ready robots {missing} "
                                      f"after {self.params['startup_timeout']} s")
        else:
            self.get_logger().info(f"all {self.num_robots} robots ready")
        self.outcome = fleet_io.run_lockstep(
            self, self.channels, self.recorder, self.positions, self._step, self._publish_state,
            decision_timeout=float(self.params["decision_timeout"]),
            tick_period=float(self.params["tick_period"]),
            progress_every=int(self.params["progress_every"]),
            record_file=self.params["record_file"], settings=self.params)

    def _step(self, decisions: Decisions):
        """The grid world's move: the arbiter's conflict rule; robots without a decision are
        held (they stay and cannot be pushed)."""
        held = np.zeros(self.num_robots, dtype=bool)
        held[decisions.missing] = True
        result = self.arbiter.resolve(self.positions, decisions.preferences, held=held)
        if result.problem:
            self.get_logger().error(f"tick {decisions.tick}: {result.problem}: all robots stay")
        self.ticker.advance()
        self.channels.publish_waypoints(result.positions)
        self.positions = result.positions
        # DCC's last action: what was executed under the shield (as the evaluator's
        # policy.executed); the robot's own choice under the paper's rule (as MAPFEnv)
        self.last_actions = result.actions if self.arbiter.shield is not None else decisions.actions
        return self.positions, int(result.collided.sum()), {
            "collided": result.collided_ids, "requested": decisions.requested,
            "messages": decisions.messages, "executed": result.actions.tolist(),
            "overridden": result.overridden_ids}

    def _publish_state(self, done: bool):
        stamp = self.channels.publish_state(self.positions, self.goals, self.last_actions, done)
        for i, pub in enumerate(self.pose_pubs):
            pub.publish(common.cell_pose(*self.positions[i], self.geometry, stamp))


@one_line_errors("simulator")
def main(argv: list[str] | None = None) -> int:
    """Run the simulator until the run ends; exit code 0 on success."""
    return fleet_io.spin_until_finished(SimulatorNode, "simulator", argv)


if __name__ == "__main__":
    sys.exit(main())
