"""Shared ROS plumbing of the fleet: QoS profiles, cell <-> pose messages, map messages, and the
process set-up every fleet process needs (environment, spin thread); the topic names and the map
geometry (conventions in docs/architecture.md) come from `mapf_fleet.fleet.topics`."""

from __future__ import annotations

import threading

import numpy as np

# The environment every fleet process runs with lives with the process plumbing (plain Python)
# and is re-exported here: common imports processes, never the other way round.
from mapf_fleet.fleet.parameters import DEVICES
from mapf_fleet.ros.processes import FLEET_ENV, prepare_environment  # noqa: F401

# The fleet's names (MAP_TOPIC ... GOAL_EVENTS_TOPIC, FRAME_ID, `rel`, `in_namespace`), the map
# geometry and the OccupancyGrid -> grid conversion live in the ROS-free fleet.topics (the
# rosbag2 reader of view.replay needs them without ROS), re-exported here.
from mapf_fleet.fleet.topics import (  # noqa: F401
    DCC_ANNOUNCE_TOPIC, DHC_HIDDEN_TOPIC, FRAME_ID, GOAL_EVENTS_TOPIC, HUB_STATUS_TOPIC, MAP_TOPIC,
    MARKERS_TOPIC, MOVE_BATCHES_TOPIC, MOVES_TOPIC, OUTCOME_TOPIC, PROGRESS_TOPIC, STATE_TOPIC,
    STATUS_TOPIC, MapGeometry, in_namespace, occupancy_to_grid, rel,
)


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


def resolve_device(device: str) -> str:
    """The torch device of parameter `device` (fleet.parameters.DEVICES), read by
    `models.policy.resolve_device`: auto is cuda when torch sees a CUDA device, else cpu;
    ValueError (one line) for cuda without one."""
    from mapf_fleet.models.policy import resolve_device as torch_device

    if device not in DEVICES:
        raise ValueError(f"parameter device must be one of {', '.join(DEVICES)}, "
                         f"got {device!r}")
    try:
        return torch_device(device).type
    except ValueError as err:
        raise ValueError(f"parameter {err}") from None
