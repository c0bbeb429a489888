"""Pictures of a fleet for people, the top layer: `picture.FleetPicture` (what the fleet's
topics say: map, robots, goals, paths taken, tick, throughput), `web` (the self-served page of
`mapf-fleet view`, fed by Server-Sent Events), `foxglove_out` (the same picture for the Foxglove
app through foxglove-sdk's WebSocket server) and `replay` (`mapf-fleet render` of a recorded run:
`up --record` JSON or a rosbag2 of `mapf-fleet record` / `up --bag`, read without ROS). Only
`live` (`mapf-fleet view`: subscribes to a running fleet) uses ROS, through `mapf_fleet.ros`."""
