"""`mapf-fleet view` on a running simulated fleet: the page, opened in headless
chromium, shows the fleet's map and its robots where the fleet says they are, and follows the
run; the Foxglove app's WebSocket server answers on loopback with the view's channels. A run
recorded with `up --record --bag` renders to a GIF from either file (`render --run`).

How the screenshot is checked (test/headless_browser.check_picture): the map comes from the
instance generator (`up --size 10 --seed 2`, not from the page), so every obstacle cell must be
obstacle-dark and every free cell light; the robots drawn (window.viewDrawn, read before and
after the screenshot, same tick) must be the record's positions at that tick (`up --record`,
read after the run), and each robot's cell centre must have that robot's colour. A blank page,
a page without the map, or robots in the wrong place fail.
"""

from __future__ import annotations

import base64
import json
import os
import signal
import socket
import subprocess
import sys
import time

import pytest

from mapf_fleet.view.live import READY_PREFIX

CLI = [sys.executable, "-m", "mapf_fleet.cli"]
SIZE, ROBOTS, SEED = 10, 4, 2
CELL = 24

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(900)]


def _start(command, env, log):
    """A child whose output goes to the file `log` (a pipe nobody reads could fill and block
    it). `env` is the test's `ros_env` (test/conftest.py): its own ROS_DOMAIN_ID and
    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, checked here before anything starts."""
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    with open(log, "w") as out:
        return subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT, text=True)


def _start_view(env, log, *extra, timeout=300.0):
    proc = _start(CLI + ["view", "--port", "0", "--foxglove-port", "0", *extra], env, log)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        url = foxglove = None
        for line in log.read_text().splitlines():
            if line.startswith(READY_PREFIX):
                url = line.split()[-1]
            elif line.startswith("mapf-fleet view: Foxglove app: ws://"):
                foxglove = int(line.split("ws://127.0.0.1:")[1].split()[0])
        if url and foxglove:
            return proc, url, foxglove
        time.sleep(0.2)
    raise AssertionError("the view did not start:\n" + log.read_text())


def _stop(proc, log, sig=signal.SIGINT, timeout=60) -> str:
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    return log.read_text()


def _foxglove_hello(port: int) -> list[dict]:
    """The first JSON messages of foxglove-sdk's server (serverInfo, advertise) after a
    WebSocket handshake with the Foxglove protocol."""
    key = base64.b64encode(os.urandom(16)).decode()
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        sock.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                      f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                      "Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n"
                      "\r\n").encode())
        stream = sock.makefile("rb")
        status = stream.readline()
        assert b" 101 " in status, status
        while stream.readline() not in (b"\r\n", b""):
            pass
        messages = []
        while len(messages) < 2:
            head = stream.read(2)
            length = head[1] & 0x7F
            if length == 126:
                length = int.from_bytes(stream.read(2), "big")
            elif length == 127:
                length = int.from_bytes(stream.read(8), "big")
            payload = stream.read(length)
            if head[0] & 0x0F == 1:  # a text frame: JSON
                messages.append(json.loads(payload))
        return messages


def _consistent_screenshot(browser):
    """A screenshot, what the page says it drew and its tick line, taken at the same tick."""
    script = ("return [window.viewDrawn, document.getElementById('tick').textContent]")
    for _ in range(50):
        before = browser.run(script)
        image = browser.screenshot()
        after = browser.run(script)
        if before == after:
            return image, after[0], after[1]
    raise AssertionError("the page never held still for a screenshot")


@pytest.mark.parametrize("namespace", ["", "/fleet_v"])
def test_the_view_shows_a_running_fleet_in_a_browser(tmp_path, ros_env, checkpoints, namespace):
    from headless_browser import Browser, check_picture, require_browser

    from mapf_fleet.grid.instance import generate_instance
    from mapf_fleet.view.replay import load_record

    require_browser()
    instance = generate_instance(SIZE, ROBOTS, 0.3, SEED)  # what `up` generates
    record = tmp_path / "run.json"
    in_ns = ["--namespace", namespace] if namespace else []
    view_log, up_log = tmp_path / "view.log", tmp_path / "up.log"
    view, url, foxglove_port = _start_view(ros_env, view_log, *in_ns)
    fleet = None

    def running():  # a fleet or view that died fails the test at once, with its output
        if fleet.poll() is not None or view.poll() is not None:
            raise AssertionError(f"up exited {fleet.poll()}, view {view.poll()}:\n"
                                 f"{up_log.read_text()}\n--- view:\n{view_log.read_text()}")
        return True

    try:
        fleet = _start(
            CLI + ["up", "--checkpoint", checkpoints["dhc"], "--num-robots", str(ROBOTS),
                   "--size", str(SIZE), "--seed", str(SEED), "--max-steps", "2000",
                   # lifelong goals: the fleet runs until the test stops it, however fast the
                   # robots reach their first goals
                   "--task-source", "lifelong",
                   "--single-process", "--record", str(record), "--quiet", *in_ns,
                   "--ros-args", "-p", "tick_period:=0.3"], ros_env, up_log)
        with Browser(width=SIZE * CELL + 420, height=SIZE * CELL + 300) as browser:
            browser.open(f"{url}?cell={CELL}")
            # live: the page follows the ticks as they come (no reload)
            browser.wait_for("return window.viewDrawn && window.viewDrawn.tick >= 2", 300,
                             running)
            first = browser.run("return window.viewDrawn.tick")
            browser.wait_for(f"return window.viewDrawn.tick >= {first + 2}", 120, running)
            image, drawn, panel = _consistent_screenshot(browser)
            image.save(tmp_path / "view.png")
            assert browser.run("return document.body.dataset.map") == f"{SIZE}x{SIZE}"
        assert drawn["cell"] == CELL
        check_picture(image, instance.grid, drawn["robots"], drawn["colours"], CELL)
        hello = _foxglove_hello(foxglove_port)
        assert hello[0]["op"] == "serverInfo", hello
        topics = {channel["topic"] for channel in hello[1]["channels"]}
        assert {"/view/scene", "/view/stats"} <= topics, hello
        up_out = _stop(fleet, up_log)
    finally:
        if fleet is not None and fleet.poll() is None:
            fleet.kill()
            fleet.wait()
        view_out = _stop(view, view_log)
    assert fleet.returncode == 130, up_out
    assert view.returncode == 0 and "Traceback" not in view_out, view_out
    run = json.loads(record.read_text())
    # the robots and goals drawn are the fleet's at the tick drawn (lifelong goals: a robot that
    # reached its first goal has another by then)
    assert drawn["episode"] == str(run["episode"])
    assert drawn["robots"] == run["positions"][drawn["tick"]], (drawn, panel)
    assert run["goals"] == instance.goals.tolist()
    recorded = load_record(record, {"size": SIZE, "seed": SEED})
    assert drawn["goals"] == recorded.goals[drawn["tick"]].tolist(), (drawn, panel)
    assert panel.startswith(f"{drawn['tick']} / 2000")


def test_a_recorded_run_renders_from_its_record_and_from_its_bag(tmp_path, ros_env, checkpoints):
    """No view here: `up --bag` starts tick 0 once /fleet/state has as many matched subscribers
    as the policy processes and the recorder, and a view's subscription would count as one (the
    bag then misses the first ticks; reported to the lead)."""
    from PIL import Image

    from mapf_fleet.cli import main as mapf_fleet
    from mapf_fleet.view.replay import load_bag

    record, bag, log = tmp_path / "run.json", tmp_path / "bag", tmp_path / "up.log"
    fleet = _start(CLI + ["up", "--checkpoint", checkpoints["dhc"], "--num-robots", str(ROBOTS),
                          "--size", str(SIZE), "--seed", str(SEED), "--max-steps", "12",
                          "--single-process", "--record", str(record), "--bag", str(bag),
                          "--quiet"], ros_env, log)
    try:
        fleet.wait(600)
    finally:
        if fleet.poll() is None:
            fleet.kill()
            fleet.wait()
    assert (bag / "metadata.yaml").exists(), log.read_text()
    run = json.loads(record.read_text())
    recorded = load_bag(bag)
    assert recorded.episode == run["episode"], log.read_text()
    assert recorded.ticks == list(range(len(run["positions"])))
    assert recorded.positions.tolist() == run["positions"]
    for source, extra in ((record, ["--size", str(SIZE), "--seed", str(SEED)]), (bag, [])):
        gif = tmp_path / f"{source.name}.gif"
        assert mapf_fleet(["render", "--run", str(source), "--out", str(gif), *extra]) == 0
        with Image.open(gif) as image:
            assert image.n_frames == len(run["positions"])
