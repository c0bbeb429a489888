"""The fleet's topic names, their namespaces, and the map's cell <-> metre geometry, without
ROS: what the ROS nodes (through `ros.common`, which re-exports them) and the offline readers of
a recorded fleet (`view.replay` reading a rosbag2) share.

Conventions (see docs/architecture.md): frame "map"; cell (row, col) has its centre at
x = origin.x + (col + 0.5) * resolution, y = origin.y + (row + 0.5) * resolution, which is how
nav_msgs/OccupancyGrid lays out its row-major data (row index along y); /fleet/map: 0 free,
100 obstacle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# The fleet's names in the default namespace (what viewers, echo and bag see there). The nodes
# create their topics and services under the RELATIVE names (`rel(...)`), resolved in the node's
# namespace: /fleet/map and /robot_3/pose by default, /fleet_a/fleet/map and
# /fleet_a/robot_3/pose with `-r __ns:=/fleet_a` (`mapf-fleet up --namespace /fleet_a`), so
# fleets in different namespaces share a ROS_DOMAIN_ID without hearing each other.
MAP_TOPIC = "/fleet/map"
STATE_TOPIC = "/fleet/state"
MOVES_TOPIC = "/fleet/moves"  # RobotMove: one robot's decision (per_robot_messages, others)
MOVE_BATCHES_TOPIC = "/fleet/move_batches"  # RobotMoves: a policy process's robots, one a tick
PROGRESS_TOPIC = "/fleet/progress"
OUTCOME_TOPIC = "/fleet/outcome"
MARKERS_TOPIC = "/fleet/markers"
STATUS_TOPIC = "/fleet/robot_status"  # RobotStatus: one robot's heartbeat (per_robot_messages)
HUB_STATUS_TOPIC = "/fleet/hub_status"  # HubStatus: a policy process's robots' heartbeat
DHC_HIDDEN_TOPIC = "/fleet/dhc/hidden"
DCC_ANNOUNCE_TOPIC = "/fleet/dcc/announce"
GOAL_EVENTS_TOPIC = "/fleet/goal_events"  # every goal change (ros.goals, msg GoalEvent)
FRAME_ID = "map"


def rel(name: str) -> str:
    """The relative form of a fleet topic or service name: resolved under the node's
    namespace (see above)."""
    return name.lstrip("/")


def in_namespace(name: str, namespace: str = "") -> str:
    """The full name of fleet topic `name` in `namespace` ('/fleet/map', '/fleet_a' ->
    '/fleet_a/fleet/map', 'fleet/map' too); a name already in the namespace is kept."""
    namespace = namespace.strip("/")
    if not namespace:
        return "/" + name.lstrip("/")
    if name.startswith("/") and name.startswith(f"/{namespace}/"):
        return name
    return f"/{namespace}/{name.lstrip('/')}"


@dataclass(frozen=True)
class MapGeometry:
    resolution: float = 1.0
    origin_x: float = 0.0
    origin_y: float = 0.0

    def __post_init__(self):
        if not self.resolution > 0:
            raise ValueError(f"map resolution must be > 0, got {self.resolution!r}")

    def cell_to_xy(self, row: int, col: int) -> tuple[float, float]:
        return (self.origin_x + (col + 0.5) * self.resolution,
                self.origin_y + (row + 0.5) * self.resolution)

    def xy_to_cell(self, x: float, y: float) -> tuple[int, int]:
        """The cell containing (x, y) (may lie outside the grid: the caller checks)."""
        return (int(np.floor((y - self.origin_y) / self.resolution)),
                int(np.floor((x - self.origin_x) / self.resolution)))


def occupancy_to_grid(msg) -> tuple[np.ndarray, MapGeometry]:
    """Obstacle grid (uint8, 1 = obstacle; unknown -1 counts as obstacle) and its geometry."""
    data = np.asarray(msg.data, dtype=np.int16).reshape(msg.info.height, msg.info.width)
    grid = ((data >= 50) | (data < 0)).astype(np.uint8)
    geometry = MapGeometry(float(msg.info.resolution), float(msg.info.origin.position.x),
                           float(msg.info.origin.position.y))
    return grid, geometry
