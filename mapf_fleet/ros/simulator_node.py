"""SimulatorNode: the grid world as a ROS node, stepping the fleet in lockstep ticks.

Tick k: publish the fleet state of k (and poses, markers); wait for every robot's move for k (a
move missing after `decision_timeout` counts as "stay" and is reported, and the robot cannot be
pushed); arbitrate the moves with `conflict_rule` (`arbiter.TickArbiter`: "pibt" = PIBT over the
robots' ranked actions, "pibt_anchor" = the same with the top-priority robot on its
distance order, their "_swap" / "_hindrance" variants and the `_epibt` / `_lns` rules (coordination.rules.CONFLICT_RULES; the
default `coordination.rules.FLEET_RULE`),
"revert" = the paper's grid.resolve_moves on their first choices);
command each robot's waypoint; publish progress; go on with k + 1. The run itself (cells, goals,
tasks, arbiter, record) is the fleet core's `fleet.run.FleetRun` (`task_source`: the one-shot
instance, lifelong goals, a task list, or external goals only); goals also come at run time
(`ros.goals.GoalServer`: goal_pose, navigate_to_pose, fleet/submit_tasks). The state's `last_actions`
are the executed actions under the PIBT rules (DCC's last-action input, as the evaluator's shield) and
the robots' first choices under "revert" (as the paper's environment). At the end the outcome
(success, steps, collisions, missed decisions) is published (latched) and optionally written to
`record_file` as JSON with the whole trajectory. The tick bookkeeping it shares with the
aggregator is in `lockstep` and `tick_loop` (plain Python) and `fleet_io` (their
base node, topics, main).
"""

from __future__ import annotations

import sys

import numpy as np
from geometry_msgs.msg import PoseStamped

from mapf_fleet.entry import one_line_errors
from mapf_fleet.fleet import parameters
from mapf_fleet.fleet.lockstep import fleet_run
from mapf_fleet.fleet.record import Decisions
from mapf_fleet.ros import common, fleet_io
from mapf_fleet.ros.goals import GoalServer

PARAMETERS = parameters.SIMULATOR  # name -> Param (fleet.parameters: the one table)


class SimulatorNode(fleet_io.LockstepNode):
    NAME = "simulator"
    PARAMETERS = PARAMETERS

    def __init__(self, **node_kwargs):
        super().__init__(**node_kwargs)
        p = self.params
        # the run: cells, goals, tasks, arbiter, record (the fleet core, shared with the
        # aggregator and the evaluator's lifelong rollout); who talked to whom: per robot its
        # partners (DHC) / requested peers (DCC), and the peer messages it used
        self.run = fleet_run(p, self.instance.grid, self.instance.starts, self.instance.goals,
                             self.episode, ("collided", "requested", "messages", "executed",
                                            "overridden"),
                             self.geometry, start_tick=int(p["start_tick"]))
        quiet = common.quiet_publisher_events()  # per-robot publishers: keep the wait set small
        self.pose_pubs = [self.create_publisher(PoseStamped, common.rel(common.pose_topic(i)),
                                                common.reliable_qos(10), event_callbacks=quiet)
                          for i in range(self.num_robots)]
        self.channels.publish_map_and_goals(self.instance.grid, self.run.goals)
        self.goals = GoalServer(self, self.run, self.lock, self.geometry,
                                robot_actions=bool(p["robot_actions"]))
        self.get_logger().info(
            f"instance {self.instance.size[0]}x{self.instance.size[1]} with {self.num_robots} "
            f"robots, conflict rule {self.conflict_rule}, task source {p['task_source']}, "
            f"episode {self.episode}")
        # tick_period, decision_timeout, progress_every apply from the next tick
        self._start_tick_thread()

    @property
    def positions(self) -> np.ndarray:
        return self.run.positions

    # ---- the lockstep loop (own thread) ----
    def _run(self):
        missing = self.ticker.wait_ready(float(self.params["startup_timeout"]),
                                         also=self.state_heard_by_fleet)
        if self.ticker.stopped:
            self.get_logger().info(f"stopped while waiting for robots {missing}")
        elif missing:
            self.get_logger().warning(f"starting without ready robots {missing} "
                                      f"after {self.params['startup_timeout']} s")
        else:
            self.get_logger().info(f"all {self.num_robots} robots ready")
        self.run_ticks(self.run)

    def _step(self, decisions: Decisions):
        """The grid world's move (`FleetRun.step`: the arbiter's rule; robots without a decision
        are held: they stay and cannot be pushed); the robots are where they were commanded."""
        result, events = self.run.step(decisions, requested=decisions.requested,
                                       messages=decisions.messages)
        if result.problem:
            self.get_logger().error(f"tick {decisions.tick}: {result.problem}: all robots stay")
        self.ticker.advance()
        # only the robots that move: the others' latched waypoint is already where they are
        self.channels.publish_waypoints(result.positions, changed_only=True)
        self.channels.publish_goal_changes(self.run.goals, events)
        return events, result.overridden_ids

    def _publish_state(self, done: bool):
        stamp = self.channels.publish_state(self.run.positions, self.run.goals,
                                            self.run.last_actions, done)
        # a robot's pose only where someone listens (a viewer, a bag): the topic is not
        # latched, and every robot's pose every tick was a large share of a large fleet's tick
        listened = [i for i, pub in enumerate(self.pose_pubs) if pub.get_subscription_count()]
        fleet_io.publish_cells(self.pose_pubs, self.run.positions, listened, self.geometry,
                               stamp)


@one_line_errors("simulator")
def main(argv: list[str] | None = None) -> int:
    """Run the simulator until the run ends; exit code 0 on success."""
    return fleet_io.spin_until_finished(SimulatorNode, "simulator", argv)


if __name__ == "__main__":
    sys.exit(main())
