"""The fleet's picture for the Foxglove app, through foxglove-sdk's WebSocket server (bound to
127.0.0.1; the app connects with "Open connection" -> Foxglove WebSocket ->
ws://127.0.0.1:PORT, or through the URL `mapf-fleet view` prints).

Channels (add a 3D panel with display frame "map", and a Raw Messages or Plot panel for the
stats):
    /view/scene   foxglove.SceneUpdate: entity "map" (a cube per obstacle cell), "goals" (flat
                  cubes), "robots" (spheres), "paths" (one line strip per robot); robot i has
                  the colour the page gives it (picture.robot_colour)
    /view/stats   JSON: episode, tick, on_goal, reached, throughput, throughput_window, outcome

Positions are the fleet's metric poses (common.MapGeometry: x along columns, y along rows), as
RViz shows /fleet/markers, so in the app row 0 is at the bottom.
"""

from __future__ import annotations

import threading

from mapf_fleet.view.picture import FleetPicture, robot_colour


class FoxgloveOut:
    def __init__(self, port: int = 8765, name: str = "mapf-fleet view"):
        import foxglove
        from foxglove.channels import SceneUpdateChannel
        from foxglove.websocket import ServerListener

        out = self

        class Listener(ServerListener):  # a newly subscribed app gets the map at once
            def on_subscribe(self, client, channel):
                if channel.topic == "/view/scene":
                    out._map_sent = -1
                    out._wake.set()

        self._map_sent = -1
        self._wake = threading.Event()
        self.server = foxglove.start_server(name=name, host="127.0.0.1", port=int(port),
                                            server_listener=Listener())
        self.port = self.server.port
        self.scene = SceneUpdateChannel("/view/scene")
        self.stats = foxglove.Channel("/view/stats")  # schemaless JSON

    def app_url(self) -> str:
        return self.server.app_url() or f"ws://127.0.0.1:{self.port}"

    def publish(self, picture: FleetPicture) -> None:
        """Send what changed: the map when it is new (or an app just subscribed), the robots,
        goals and paths, and the stats."""
        from foxglove.messages import SceneUpdate

        entities = []
        if picture.map_version != self._map_sent:
            self._map_sent = picture.map_version
            entities.append(self._map_entity(picture))
        snapshot = picture.snapshot()
        if snapshot["tick"] is not None:
            entities += self._fleet_entities(picture, snapshot)
            self.stats.log({key: snapshot[key] for key in (
                "episode", "tick", "done", "on_goal", "reached", "throughput",
                "throughput_window", "window", "progress", "outcome")})
        if entities:
            self.scene.log(SceneUpdate(entities=entities))

    def republish_if_asked(self, picture: FleetPicture) -> None:
        """Called periodically: a client that subscribed since gets the map."""
        if self._wake.is_set():
            self._wake.clear()
            self.publish(picture)

    def stop(self) -> None:
        self.server.stop()

    # ---- entities ---------------------------------------------------------------------------
    @staticmethod
    def _xy(picture, row, col):
        g = picture.geometry
        return (g["origin_x"] + (col + 0.5) * g["resolution"],
                g["origin_y"] + (row + 0.5) * g["resolution"])

    def _map_entity(self, picture):
        from foxglove.messages import Color, CubePrimitive, Pose, SceneEntity, Vector3

        res = picture.geometry["resolution"]
        cubes = []
        if picture.grid is not None:
            size = Vector3(x=res, y=res, z=res * 0.5)
            colour = Color(r=0.15, g=0.15, b=0.15, a=1.0)
            for row, col in zip(*picture.grid.nonzero()):
                x, y = self._xy(picture, int(row), int(col))
                cubes.append(CubePrimitive(pose=Pose(position=Vector3(x=x, y=y, z=res * 0.25)),
                                           size=size, color=colour))
        return SceneEntity(frame_id="map", id="map", cubes=cubes)

    def _fleet_entities(self, picture, snapshot):
        from foxglove.messages import (Color, CubePrimitive, LinePrimitive, Point3, Pose,
                                       SceneEntity, SpherePrimitive, Vector3)

        res = picture.geometry["resolution"]

        def colour(i, alpha=1.0):
            r, g, b = robot_colour(i)
            return Color(r=r / 255, g=g / 255, b=b / 255, a=alpha)

        def at(cell, z):
            x, y = self._xy(picture, *cell)
            return Pose(position=Vector3(x=x, y=y, z=z))

        robots = [SpherePrimitive(pose=at(cell, res * 0.4), size=Vector3(
            x=res * 0.76, y=res * 0.76, z=res * 0.76), color=colour(i))
            for i, cell in enumerate(snapshot["robots"])]
        goals = [CubePrimitive(pose=at(cell, 0.02 * res), size=Vector3(
            x=res * 0.72, y=res * 0.72, z=0.04 * res), color=colour(i, 0.6))
            for i, cell in enumerate(snapshot["goals"])]
        paths = [LinePrimitive(thickness=res * 0.15, color=colour(i, 0.5), points=[
            Point3(x=x, y=y, z=0.05 * res) for x, y in (self._xy(picture, *c) for c in trail)])
            for i, trail in enumerate(snapshot["trails"]) if len(trail) > 1]
        return [SceneEntity(frame_id="map", id="robots", spheres=robots),
                SceneEntity(frame_id="map", id="goals", cubes=goals),
                SceneEntity(frame_id="map", id="paths", lines=paths)]
