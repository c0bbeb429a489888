"""Pictures of a fleet for people (no rclpy here): `picture.FleetPicture` (what the fleet's
topics say: map, robots, goals, paths taken, tick, throughput), `web` (the self-served page of
`mapf-fleet view`, fed by Server-Sent Events), `foxglove_out` (the same picture for the Foxglove
app through foxglove-sdk's WebSocket server) and `replay` (`mapf-fleet render` of a recorded run:
`up --record` JSON or a rosbag2 of `mapf-fleet record` / `up --bag`). The ROS side is
`mapf_fleet.ros.live_view`."""
