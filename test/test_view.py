"""The live view without ROS: the picture's bookkeeping (paths, goals reached, throughput, goals
that change during a run, a new episode), the page server (loopback only, the page from package
data, /state.json, Server-Sent Events), and the page itself in headless chromium drawing a
picture fed here (map and robots checked pixel by pixel)."""

from __future__ import annotations

import glob
import json
import socket
import threading
import urllib.error
import urllib.request

import numpy as np
import pytest

from mapf_fleet.view.picture import FleetPicture, robot_colour
from mapf_fleet.view.web import ViewServer, page_html

GRID = np.array([[0, 0, 0, 1],
                 [0, 1, 0, 0],
                 [0, 0, 0, 0]], np.uint8)


# ---- the picture ------------------------------------------------------------------------------
def test_paths_and_goals_reached_once_per_goal():
    p = FleetPicture(window=4)
    p.set_map(GRID)
    goals = [(0, 2), (2, 3)]
    p.set_state(5, 0, [(0, 0), (2, 0)], goals)
    p.set_state(5, 1, [(0, 1), (2, 1)], goals)
    p.set_state(5, 2, [(0, 2), (2, 1)], goals)      # robot 0 reached
    p.set_state(5, 3, [(0, 1), (2, 2)], goals)      # pushed off
    p.set_state(5, 4, [(0, 2), (2, 3)], goals)      # back (no second count), robot 1 reached
    snap = p.snapshot()
    assert snap["reached"] == 2 and snap["on_goal"] == 2 and snap["reached_by"] == "view"
    assert snap["trails"][0] == [[0, 0], [0, 1], [0, 2], [0, 1], [0, 2]]
    assert snap["trails"][1] == [[2, 0], [2, 1], [2, 2], [2, 3]]  # a stay adds no cell
    assert snap["throughput"] == pytest.approx(2 / 4)
    assert snap["colours"] == ["#%02x%02x%02x" % robot_colour(i) for i in range(2)]


def test_goals_given_during_a_run_are_drawn_and_counted():
    p = FleetPicture()
    p.set_state(1, 0, [(0, 0)], [(0, 1)])
    # it arrived on (0, 1) in the tick its next goal was given: that goal counts as reached
    p.set_state(1, 1, [(0, 1)], [(2, 2)])
    assert p.snapshot()["goals"] == [[2, 2]] and p.reached == 1
    p.set_state(1, 2, [(1, 2)], [(2, 2)])
    p.set_state(1, 3, [(2, 2)], [(2, 2)])
    assert p.reached == 2
    p.set_state(1, 4, [(2, 2)], [(0, 0)])  # a new goal while on the old, already counted
    assert p.reached == 2


def test_a_new_episode_starts_afresh_and_late_states_are_ignored():
    p = FleetPicture()
    p.set_state(1, 0, [(0, 0)], [(0, 0)])
    p.set_state(1, 3, [(0, 1)], [(0, 0)])
    p.set_state(1, 2, [(0, 2)], [(0, 0)])  # older than what is shown
    assert p.snapshot()["robots"] == [[0, 1]]
    p.set_outcome(True, "success: 1/1", episode=1)
    p.set_state(2, 0, [(2, 0), (2, 1)], [(0, 0), (0, 2)])
    snap = p.snapshot()
    assert snap["episode"] == "2" and snap["reached"] == 0 and snap["outcome"] == {}
    assert snap["trails"] == [[[2, 0]], [[2, 1]]]
    p.set_outcome(True, "the old run's latched outcome", episode=1)
    assert p.snapshot()["outcome"] == {}


def test_the_fleets_own_goal_count_wins_and_gives_the_throughput():
    p = FleetPicture(window=10)
    p.set_state(3, 40, [(0, 0)], [(1, 1)])  # a view started at tick 40 of a continuous run
    for tick in range(40, 61):
        p.set_progress(episode=3, tick=tick, goals_reached=tick // 2)
    snap = p.snapshot()
    assert snap["reached"] == 30 and snap["reached_by"] == "fleet"
    assert snap["throughput"] == pytest.approx(30 / 60)
    assert snap["throughput_window"] == pytest.approx((30 - 25) / 10)
    assert snap["window_ticks"] == 10
    p.set_progress(episode=4, tick=1, goals_reached=99)  # another run's progress: not ours
    assert p.reached == 30


def test_bad_states_are_refused():
    p = FleetPicture()
    with pytest.raises(ValueError, match="2 robots but 1 goals"):
        p.set_state(1, 0, [(0, 0), (1, 1)], [(0, 0)])
    with pytest.raises(ValueError, match="non-empty 2-D grid"):
        p.set_map(np.zeros((0, 3)))


# ---- the server -------------------------------------------------------------------------------
@pytest.fixture
def served():
    picture = FleetPicture()
    server = ViewServer(picture, 0).start()
    yield picture, server
    server.stop()


def _get(url, host=None, timeout=10):
    request = urllib.request.Request(url, headers={"Host": host} if host else {})
    with urllib.request.urlopen(request, timeout=timeout) as response:
        return response.status, response.headers.get("Content-Type"), response.read()


def test_the_page_is_package_data_and_is_served_on_loopback_only(served):
    picture, server = served
    assert server.url.startswith("http://127.0.0.1:")
    assert server.httpd.server_address[0] == "127.0.0.1"
    status, kind, body = _get(server.url)
    assert status == 200 and kind.startswith("text/html") and b"<canvas" in body
    assert body == page_html().replace(b"{{TITLE}}", b"mapf-fleet view")
    with pytest.raises(urllib.error.HTTPError) as refused:  # DNS rebinding: another host name
        _get(server.url, host=f"attacker.example:{server.port}")
    assert refused.value.code == 403
    with pytest.raises(urllib.error.HTTPError) as missing:
        _get(server.url + "nothing")
    assert missing.value.code == 404


def test_state_json_and_the_event_stream(served):
    picture, server = served
    picture.set_map(GRID, resolution=0.5)
    picture.set_state(9, 0, [(0, 0)], [(2, 3)])
    state = json.loads(_get(server.url + "state.json")[2])
    assert state["tick"] == 0 and state["robots"] == [[0, 0]] and state["has_map"]
    with urllib.request.urlopen(server.url + "events", timeout=10) as stream:
        assert stream.headers.get("Content-Type") == "text/event-stream"
        events = []
        while len(events) < 3:
            line = stream.readline().decode()
            if line.startswith("data: "):
                events.append(json.loads(line[6:]))
                if len(events) == 2:  # the map and the state came: one more tick
                    picture.set_state(9, 1, [(1, 0)], [(2, 3)])
    assert events[0]["type"] == "map" and events[0]["rows"] == ["0001", "0100", "0000"]
    assert events[0]["resolution"] == 0.5
    assert [e["tick"] for e in events[1:]] == [0, 1]
    assert events[2]["trails"] == [[[0, 0], [1, 0]]]


def test_a_busy_port_is_refused_by_the_command(capsys):
    from mapf_fleet.cli import main

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        port = sock.getsockname()[1]
        assert main(["view", "--port", str(port), "--no-foxglove"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"mapf-fleet view: cannot serve the page on 127.0.0.1:{port}")
    assert len(err.strip().splitlines()) == 1


def test_setup_installs_the_page():
    from setup_info import setup_kwargs

    patterns = setup_kwargs()["package_data"]["mapf_fleet.view"]
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "mapf_fleet" / "view"
    installed = {Path(f).relative_to(root).as_posix() for pattern in patterns
                 for f in glob.glob(str(root / pattern))}
    assert "static/index.html" in installed


def test_the_help_lists_the_view(capsys):
    from mapf_fleet.cli import main

    assert main(["--help"]) == 0
    assert any(line.split()[:1] == ["view"] for line in capsys.readouterr().out.splitlines())


# ---- the page in a real browser ---------------------------------------------------------------
@pytest.mark.slow
def test_the_page_draws_map_robots_and_follows_the_stream(served):
    from headless_browser import Browser, check_picture

    from mapf_fleet.grid.instance import generate_instance

    picture, server = served
    instance = generate_instance(12, 5, 0.3, 3)
    picture.set_map(instance.grid)
    picture.set_state(11, 0, instance.starts, instance.goals)
    cell = 24
    with Browser(width=12 * cell + 400, height=12 * cell + 100) as browser:
        # no trails: the robots jump to their goals below (no legal move), and the straight
        # lines of such jumps cross obstacle cells
        browser.open(server.url + f"?cell={cell}&trail=0")
        browser.wait_for("return window.viewDrawn && window.viewDrawn.tick === 0")
        image = browser.screenshot()
        colours = browser.run("return window.viewDrawn.colours")
        check_picture(image, instance.grid, instance.starts, colours, cell)
        # the page follows the stream: the robots' next cells (a tick later) are drawn there
        moved = np.array(instance.goals)
        picture.set_state(11, 1, moved, instance.goals)
        browser.wait_for("return window.viewDrawn.tick === 1")
        check_picture(browser.screenshot(), instance.grid, moved, colours, cell)
        assert browser.run("return document.getElementById('ongoal').textContent") == "5 / 5"
    # a check that can fail: the first picture does not show the robots where they went
    with pytest.raises(AssertionError, match="robot"):
        check_picture(image, instance.grid, moved, colours, cell)


# ---- the Foxglove side ------------------------------------------------------------------------
class _FoxgloveClient:
    """The smallest Foxglove WebSocket protocol client: handshake, JSON ops, binary messages."""

    def __init__(self, port: int):
        import base64
        import os

        self.sock = socket.create_connection(("127.0.0.1", port), timeout=30)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                           "Sec-WebSocket-Version: 13\r\n"
                           "Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n").encode())
        self.stream = self.sock.makefile("rb")
        assert b" 101 " in self.stream.readline()
        while self.stream.readline() not in (b"\r\n", b""):
            pass

    def frame(self):
        """(opcode, payload) of the next frame."""
        head = self.stream.read(2)
        length = head[1] & 0x7F
        if length == 126:
            length = int.from_bytes(self.stream.read(2), "big")
        elif length == 127:
            length = int.from_bytes(self.stream.read(8), "big")
        return head[0] & 0x0F, self.stream.read(length)

    def send_json(self, data: dict):
        import os

        payload = json.dumps(data).encode()
        mask = os.urandom(4)
        head = bytes([0x81]) + (bytes([0x80 | len(payload)]) if len(payload) < 126 else
                                bytes([0x80 | 126]) + len(payload).to_bytes(2, "big"))
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))

    def close(self):
        self.sock.close()


def test_the_foxglove_app_gets_the_scene_and_the_stats():
    from mapf_fleet.view.foxglove_out import FoxgloveOut

    picture = FleetPicture()
    picture.set_map(GRID)
    picture.set_state(4, 0, [(0, 0), (2, 0)], [(0, 2), (2, 3)])
    out = FoxgloveOut(port=0)
    client = None
    try:
        out.publish(picture)  # nobody listens yet: the map goes again on subscription
        client = _FoxgloveClient(out.port)
        channels = {}
        while len(channels) < 2:
            opcode, payload = client.frame()
            if opcode == 1:
                message = json.loads(payload)
                for channel in message.get("channels", []) if message["op"] == "advertise" else []:
                    channels[channel["topic"]] = channel
        assert channels["/view/scene"]["schemaName"] == "foxglove.SceneUpdate"
        assert channels["/view/stats"]["encoding"] == "json"
        client.send_json({"op": "subscribe", "subscriptions": [
            {"id": 1, "channelId": channels["/view/scene"]["id"]},
            {"id": 2, "channelId": channels["/view/stats"]["id"]}]})
        got = {}
        stop = threading.Event()

        def ticks():  # the fleet goes on while the subscription is being set up
            tick = 1
            while not stop.wait(0.1):
                out.republish_if_asked(picture)
                picture.set_state(4, tick, [(0, 1), (2, 1)], [(0, 2), (2, 3)])
                out.publish(picture)
                tick += 1

        publisher = threading.Thread(target=ticks, daemon=True)
        publisher.start()
        try:
            while len(got) < 2:
                opcode, payload = client.frame()
                if opcode == 2 and payload[0] == 1:  # message data: op, subscription, time, data
                    got.setdefault(int.from_bytes(payload[1:5], "little"), payload[13:])
        finally:
            stop.set()
            publisher.join(10)
        stats = json.loads(got[2])
        assert stats["episode"] == "4" and stats["reached"] == 0 and "throughput" in stats
        # the scene is protobuf; its entity ids are plain strings in it
        assert all(name in got[1] for name in (b"robots", b"goals", b"paths"))
    finally:
        if client is not None:
            client.close()
        out.stop()


def test_the_view_package_never_imports_rclpy():
    """mapf_fleet/view is read by the renderer and the tests without ROS; only
    mapf_fleet/view/live.py talks to the fleet (checked like test_layering does)."""
    from pathlib import Path

    from test_layering import imports_of

    folder = Path(__file__).resolve().parents[1] / "mapf_fleet" / "view"
    bad = [f"{path.name}:{line} imports {module}" for path in sorted(folder.rglob("*.py"))
           for line, module in imports_of(path) if module.split(".")[0] == "rclpy"]
    assert not bad and len(list(folder.rglob("*.py"))) >= 5, bad


def test_idle_robots_and_robots_starting_on_their_goal_reach_nothing():
    """An idle robot's goal is its own cell, updated every tick (mapf_fleet.fleet.run)."""
    p = FleetPicture()
    p.set_state(6, 0, [(0, 0), (2, 2)], [(0, 0), (2, 3)])  # robot 0 starts on its goal
    p.set_state(6, 1, [(0, 1), (2, 3)], [(0, 1), (2, 3)])  # robot 0 idle, moving; 1 arrives
    p.set_state(6, 2, [(1, 1), (2, 3)], [(1, 1), (2, 3)])
    p.set_state(6, 3, [(1, 1), (2, 3)], [(0, 3), (2, 3)])  # robot 0 gets a task
    p.set_state(6, 4, [(0, 3), (2, 3)], [(0, 3), (2, 3)])  # and reaches it
    assert p.reached == 2


def test_a_favicon_request_gets_no_content_and_no_traceback(served, capfd):
    _, server = served
    status, _, body = _get(server.url + "favicon.ico")
    assert status == 204 and body == b""
    assert "Traceback" not in capfd.readouterr().err
