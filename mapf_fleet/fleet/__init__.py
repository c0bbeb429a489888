"""The fleet core (numpy only, no rclpy, no torch): what a run of the fleet is without ROS.

`run.FleetRun` (grid, cells, goals, last actions, the arbiter, the recorder, the task source;
one tick = `resolve` + `advance`), `arbiter` (the tick's conflict rule and the real-robot
safety checks), `tasks` (instance, lifelong, task lists, external goals) and `record` (the
run's record and goal events). The simulator node, the real-robot aggregator and the evaluator's
lifelong rollout are adapters around it.
"""
