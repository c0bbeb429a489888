"""`mapf-fleet view`: a live picture of a running fleet in a browser on this machine.

    mapf-fleet view                       # then open the printed http://127.0.0.1:8780/
    mapf-fleet view --namespace /fleet_a  # the fleet of `up --namespace /fleet_a`

It subscribes to the fleet's topics, /fleet/map (latched), /fleet/state (every tick: the robots'
cells and their current goals), /fleet/progress and /fleet/outcome (under --namespace as `echo`
does), keeps one `view.picture.FleetPicture` (map, robots, goals, the paths taken, the tick, the
goals reached and the throughput: goals reached per tick) and serves it twice, on loopback only:

- a page of its own (`view.web`): http://127.0.0.1:PORT/ (canvas + Server-Sent Events; also
  /state.json);
- the Foxglove app (`view.foxglove_out`, foxglove-sdk's WebSocket server on ws://127.0.0.1:
  FOXGLOVE_PORT): channels /view/scene (3D panel, frame "map") and /view/stats.

The view can start before or after the fleet, and keeps running across runs: a new run (a new
episode id) starts the paths and counts afresh. SIGINT/SIGTERM end it (exit 0).
"""

from __future__ import annotations

import argparse
import sys

from mapf_fleet.ros import common

READY_PREFIX = "mapf-fleet view: page on"
DEFAULT_PORT = 8780
DEFAULT_FOXGLOVE_PORT = 8765


def subscribe(node, picture, namespace: str = "") -> None:
    """The view's subscriptions on `node`, feeding `picture`."""
    from mapf_fleet_interfaces.msg import FleetOutcome, FleetProgress, FleetState
    from nav_msgs.msg import OccupancyGrid

    def on_map(msg):
        grid, geometry = common.occupancy_to_grid(msg)
        picture.set_map(grid, geometry.resolution, geometry.origin_x, geometry.origin_y)

    def on_state(msg):
        picture.set_state(int(msg.episode), int(msg.tick), list(zip(msg.rows, msg.cols)),
                          list(zip(msg.goal_rows, msg.goal_cols)), bool(msg.done))

    def on_progress(msg):
        # goals_reached: only fleets whose FleetProgress counts goals (continuous runs) have it
        reached = getattr(msg, "goals_reached", None)
        picture.set_progress(episode=int(msg.episode), tick=int(msg.tick),
                             max_steps=int(msg.max_steps), on_goal=int(msg.on_goal),
                             collisions=int(msg.collisions),
                             missed_decisions=int(msg.missed_decisions),
                             goals_reached=None if reached is None else int(reached))

    def on_outcome(msg):
        picture.set_outcome(bool(msg.success), str(msg.summary), int(msg.episode))

    def guarded(name, callback):
        """A malformed message is reported (at most every 5 s) and skipped: an exception in a
        callback would stop the spin thread, and the view would freeze."""
        def run(msg):
            try:
                callback(msg)
            except (ValueError, TypeError, IndexError) as exc:
                node.get_logger().warning(f"{name}: message skipped: {exc}",
                                          throttle_duration_sec=5.0)
        return run

    for kind, name, callback, qos in (
            (OccupancyGrid, common.MAP_TOPIC, on_map, common.latched_qos()),
            (FleetState, common.STATE_TOPIC, on_state, common.reliable_qos(10)),
            (FleetProgress, common.PROGRESS_TOPIC, on_progress, common.reliable_qos(10)),
            (FleetOutcome, common.OUTCOME_TOPIC, on_outcome, common.latched_qos())):
        topic = common.in_namespace(name, namespace)
        node.create_subscription(kind, topic, guarded(topic, callback), qos)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mapf-fleet view", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--namespace", default="",
                        help="the fleet's namespace (`up --namespace`): /NS/fleet/state, ...")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT,
                        help=f"the page's port on 127.0.0.1 (default {DEFAULT_PORT}; 0: any free)")
    parser.add_argument("--foxglove-port", type=int, default=DEFAULT_FOXGLOVE_PORT,
                        help="foxglove-sdk's WebSocket port on 127.0.0.1 for the Foxglove app "
                             f"(default {DEFAULT_FOXGLOVE_PORT}; 0: any free)")
    parser.add_argument("--no-foxglove", action="store_true",
                        help="serve only the page, no Foxglove WebSocket server")
    parser.add_argument("--trail", type=int, default=500,
                        help="cells of each robot's path taken that are shown (default 500)")
    parser.add_argument("--window", type=int, default=50,
                        help="ticks of the recent throughput (default 50)")
    parser.add_argument("--max-rate", type=float, default=20.0,
                        help="at most this many pictures a second to a viewer (default 20)")
    return parser


def _port_ok(value: int) -> bool:
    return 0 <= value <= 65535


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if not _port_ok(args.port) or not _port_ok(args.foxglove_port):
        parser.error(f"ports must be in 0..65535, got --port {args.port} "
                     f"--foxglove-port {args.foxglove_port}")
    if args.trail < 1 or args.window < 1 or not args.max_rate > 0:
        parser.error("--trail and --window must be >= 1 and --max-rate > 0")
    from mapf_fleet.ros.echo import ros_command
    from mapf_fleet.view.picture import FleetPicture
    from mapf_fleet.view.web import ViewServer

    picture = FleetPicture(trail=args.trail, window=args.window)
    title = "mapf-fleet view" + (f" {args.namespace}" if args.namespace.strip("/") else "")
    try:
        server = ViewServer(picture, args.port, args.max_rate, title=title)
    except OSError as exc:
        print(f"mapf-fleet view: cannot serve the page on 127.0.0.1:{args.port}: "
              f"{exc.strerror or exc} (choose another --port, or 0)", file=sys.stderr)
        return 2
    foxglove = None
    if not args.no_foxglove:
        try:
            from mapf_fleet.view.foxglove_out import FoxgloveOut

            foxglove = FoxgloveOut(args.foxglove_port, name=title)
        except Exception as exc:  # foxglove-sdk raises its own error types for a busy port
            server.httpd.server_close()
            print(f"mapf-fleet view: cannot start the Foxglove server on 127.0.0.1:"
                  f"{args.foxglove_port}: {exc} (choose another --foxglove-port, 0, or "
                  "--no-foxglove)", file=sys.stderr)
            return 2
    server.start()
    try:
        with ros_command("mapf_fleet_view") as (node, stop):
            subscribe(node, picture, args.namespace)
            print(f"{READY_PREFIX} {server.url}", flush=True)
            if foxglove is not None:
                print(f"mapf-fleet view: Foxglove app: ws://127.0.0.1:{foxglove.port} "
                      f"({foxglove.app_url()})", flush=True)
            sent = -1
            interval = 1.0 / args.max_rate
            while not stop.wait(interval):
                if foxglove is not None:
                    if picture.version != sent:
                        sent = picture.version
                        foxglove.publish(picture)
                    else:
                        foxglove.republish_if_asked(picture)
    finally:
        server.stop()
        if foxglove is not None:
            foxglove.stop()
    return 0
