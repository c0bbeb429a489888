"""Shared ROS plumbing of the fleet: topic names, QoS profiles, cell <-> pose conversion, map
messages, and the process set-up every fleet process needs (environment, spin thread).

Conventions (see docs/architecture.md):
- frame "map"; cell (row, col) has its centre at x = origin.x + (col + 0.5) * resolution,
  y = origin.y + (row + 0.5) * resolution, which is how nav_msgs/OccupancyGrid lays out its
  row-major data (row index along y).
- /fleet/map: 0 free, 100 obstacle.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

# The environment every fleet process runs with lives with the process plumbing (plain Python)
# and is re-exported here: common imports processes, never the other way round.
from mapf_fleet.ros.processes import FLEET_ENV, prepare_environment  # noqa: F401

# The fleet's names in the default namespace (what viewers, echo and bag see there). The nodes
# create their topics and services under the RELATIVE names (`rel(...)`), resolved in the node's
# namespace: /fleet/map and /robot_3/pose by default, /fleet_a/fleet/map and
# /fleet_a/robot_3/pose with `-r __ns:=/fleet_a` (`mapf-fleet up --namespace /fleet_a`), so
# fleets in different namespaces share a ROS_DOMAIN_ID without hearing each other.
MAP_TOPIC = "/fleet/map"
STATE_TOPIC = "/fleet/state"
MOVES_TOPIC = "/fleet/moves"
PROGRESS_TOPIC = "/fleet/progress"
OUTCOME_TOPIC = "/fleet/outcome"
MARKERS_TOPIC = "/fleet/markers"
STATUS_TOPIC = "/fleet/robot_status"
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


def robot_ns(robot_id: int) -> str:
    return f"/robot_{int(robot_id)}"


def pose_topic(robot_id: int) -> str:
    return f"{robot_ns(robot_id)}/pose"


def goal_topic(robot_id: int) -> str:
    return f"{robot_ns(robot_id)}/goal"


def waypoint_topic(robot_id: int) -> str:
    return f"{robot_ns(robot_id)}/waypoint"


def dcc_request_service(robot_id: int) -> str:
    return f"{robot_ns(robot_id)}/dcc_request"


def dcc_reply_service(robot_id: int) -> str:
    return f"{robot_ns(robot_id)}/dcc_reply"


def init_process(args: list[str]):
    """`rclpy.init(args)` for a fleet process, with SIGINT / SIGTERM caught by the returned
    `processes.StopSignals` instead of rclpy's handlers (which would invalidate the context under
    a running publisher): the process ends its work and exits 130 / 143."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from mapf_fleet.ros.processes import stop_signals

    signals = stop_signals()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    return signals


def latched_qos(depth: int = 1):
    """Reliable, transient local: late subscribers (viewers, restarted nodes) get the last value."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def reliable_qos(depth: int = 100):
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def quiet_publisher_events():
    """Publisher options without the default QoS-event handlers: each handler is one more entity
    that the Python executor re-adds to its wait set on every spin, which dominated the
    one-process fleet's time with a few hundred publishers (benchmarks/bench_fleet.py)."""
    from rclpy.event_handler import PublisherEventCallbacks

    return PublisherEventCallbacks(use_default_callbacks=False)


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


def grid_to_occupancy(grid: np.ndarray, geometry: MapGeometry, stamp=None):
    from nav_msgs.msg import OccupancyGrid

    msg = OccupancyGrid()
    msg.header.frame_id = FRAME_ID
    if stamp is not None:
        msg.header.stamp = stamp
    height, width = grid.shape
    msg.info.resolution = float(geometry.resolution)
    msg.info.width = int(width)
    msg.info.height = int(height)
    msg.info.origin.position.x = float(geometry.origin_x)
    msg.info.origin.position.y = float(geometry.origin_y)
    msg.info.origin.orientation.w = 1.0
    msg.data = (np.asarray(grid, dtype=np.int8).reshape(-1) * 100).astype(np.int8).tolist()
    return msg


def occupancy_to_grid(msg) -> tuple[np.ndarray, MapGeometry]:
    """Obstacle grid (uint8, 1 = obstacle; unknown -1 counts as obstacle) and its geometry."""
    data = np.asarray(msg.data, dtype=np.int16).reshape(msg.info.height, msg.info.width)
    grid = ((data >= 50) | (data < 0)).astype(np.uint8)
    geometry = MapGeometry(float(msg.info.resolution), float(msg.info.origin.position.x),
                           float(msg.info.origin.position.y))
    return grid, geometry


def cell_pose(row: int, col: int, geometry: MapGeometry, stamp=None):
    from geometry_msgs.msg import PoseStamped

    msg = PoseStamped()
    msg.header.frame_id = FRAME_ID
    if stamp is not None:
        msg.header.stamp = stamp
    msg.pose.position.x, msg.pose.position.y = geometry.cell_to_xy(int(row), int(col))
    msg.pose.orientation.w = 1.0
    return msg


class SpinThread:
    """Spin an executor in its own thread (never call
    spin_until_future_complete in a loop); `stop()` ends the thread, then shuts the executor
    down, which must happen before the nodes are destroyed.

    The thread runs `spin_once` in a loop that checks its own stop flag, and `stop()` shuts the
    executor down only once the thread has left it. rclpy's `Executor.shutdown()` called while
    another thread spins is racy (Jazzy): it destroys the executor's wake-up guard condition
    without waiting for the spinning thread, so a thread that is between its shutdown check and
    building its wait set waits forever without that guard, holding the node's handles, and
    `destroy_node` then blocks (an `echo` stopped during discovery hung past 30 s under CI
    load). `stop()` hands the executor an empty task: `spin_once` runs it and returns, so the
    thread sees its flag at once (a bare `wake()` does not end `spin_once`: the executor's own
    guard yields no work and it waits on). The task's guard trigger stays set until a wait takes
    it and tasks are checked before each wait, so no wake-up is lost; the `spin_once` timeout
    bounds the wait regardless.

    A callback that raises never ends the thread silently: the exception is logged with its
    traceback (on the logger of the executor's first node), kept in `error`, passed to
    `on_error`, and the thread stops spinning; the process's main loop then ends the process
    with a non-zero code (`fleet_io.spin_until_finished`, `policy_node.spin_policy_nodes`).
    Bad input a node expects (a NaN pose) is handled in its callback and never gets here. A
    context or executor shut down under it ends it quietly."""

    # longest wait in one spin_once: the stop flag is seen this soon even without a wake-up
    POLL_S = 0.5

    def __init__(self, executor, on_error=None):
        self.executor = executor
        self.on_error = on_error
        self.error: BaseException | None = None
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ros-spin", daemon=True)

    def _run(self):
        from rclpy.executors import ExternalShutdownException, ShutdownException

        try:
            while not self._stopping.is_set() and self.executor.context.ok():
                self.executor.spin_once(timeout_sec=self.POLL_S)
        except (ExternalShutdownException, ShutdownException):
            pass
        except Exception as exc:
            if self._stopping.is_set() or not self.executor.context.ok():
                return  # shut down under us: nothing left to do
            self.error = exc
            log_callback_error(self.executor, exc)
            if self.on_error is not None:
                self.on_error(exc)

    def start(self) -> "SpinThread":
        self._thread.start()
        return self

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def stop(self, timeout: float = 5.0):
        self._stopping.set()
        try:
            self.executor.create_task(lambda: None)
        except Exception:  # the executor was already shut down (its guard is gone)
            pass
        self._thread.join(timeout)
        self.executor.shutdown(timeout_sec=timeout)


def log_callback_error(executor, exc: BaseException) -> None:
    """Log a callback's exception with its traceback on the executor's first node's logger."""
    import traceback

    import rclpy.logging

    nodes = executor.get_nodes()
    logger = nodes[0].get_logger() if nodes else rclpy.logging.get_logger("mapf_fleet")
    text = "".join(traceback.format_exception(exc)).rstrip()
    logger.error(f"a callback failed: {exc!r}; this process stops (exit code 1)\n{text}")


def split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """(own arguments, ROS arguments): everything from `--ros-args` on belongs to rclpy."""
    if "--ros-args" in argv:
        index = argv.index("--ros-args")
        return argv[:index], argv[index:]
    return list(argv), []
