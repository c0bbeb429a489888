"""`mapf-fleet echo` and `mapf-fleet topics` against stand-in publishers (test/ros/graph_helper.py):
QoS matched to the publisher (a latched topic read late still arrives), clean end on
SIGINT/SIGTERM, and `topics` waiting for discovery to settle."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

HELPER = str(Path(__file__).with_name("graph_helper.py"))
CLI = [sys.executable, "-m", "mapf_fleet.cli"]


class Processes:
    """Helper processes of one test, ended (SIGINT, then SIGKILL) when the test ends."""

    def __init__(self, env):
        # env is ros_env (test/conftest.py): ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, own domain
        assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
        self.env = env
        self.procs: list[subprocess.Popen] = []

    def helper(self, *args: str, wait_for: str | None = "ready", timeout: float = 30.0):
        proc = subprocess.Popen([sys.executable, HELPER, *args], env=self.env, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        self.procs.append(proc)
        if wait_for is not None:
            wait_line(proc, wait_for, timeout)
        return proc

    def cli(self, *args: str, **kwargs) -> subprocess.Popen:
        proc = subprocess.Popen([*CLI, *args], env=self.env, text=True, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, **kwargs)
        self.procs.append(proc)
        return proc

    def close(self):
        for proc in self.procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in self.procs:
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def wait_line(proc: subprocess.Popen, text: str, timeout: float) -> None:
    """Read proc's stdout until a line equal to `text` (the helpers print few lines)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if line.strip() == text:
            return
        if not line and proc.poll() is not None:
            raise AssertionError(f"helper ended ({proc.returncode}) before {text!r}: "
                                 f"{proc.stderr.read()}")
    raise AssertionError(f"no {text!r} from the helper within {timeout} s")


def wait_handlers(proc: subprocess.Popen, timeout: float) -> bool:
    """Wait until `proc` has installed its stop handlers (or has ended): SIGTERM is caught
    (Python has a SIGINT handler from the start, not a SIGTERM one; the commands install both
    together)."""
    from mapf_fleet.ros.processes import signal_disposition

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None or signal_disposition(proc.pid, signal.SIGTERM) == "caught":
            return True
        time.sleep(0.05)
    return False


@pytest.fixture
def procs(ros_env):
    group = Processes(ros_env)
    yield group
    group.close()


def run_echo(procs: Processes, *args: str, timeout: float = 40.0):
    proc = procs.cli("echo", *args)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"echo {' '.join(args)} printed nothing within {timeout} s\n{out}\n{err}")
    return proc.returncode, out, err


@pytest.mark.ros
def test_echo_once_prints_the_map_latched_before_echo_started(procs):
    """The fleet's layout: processes subscribing to /fleet/map (the policy hubs), then the
    simulator publishes the map once, then echo starts. Echo often discovers the topic through a
    subscriber before the publisher; choosing QoS at that moment gave a volatile subscription
    that never printed (about 1 try in 3 here; 5 of 5 in a busy fleet). Each round starts a new
    publisher process, so each round runs the discovery race again."""
    for _ in range(4):
        procs.helper("subscriber", "/fleet/map")
    for round_ in range(5):
        publisher = procs.helper("latched", "/fleet/map")
        code, out, err = run_echo(procs, "/fleet/map", "--once", timeout=30.0)
        assert code == 0, f"round {round_}: {err}"
        assert "resolution: 0.5" in out and out.rstrip().endswith("---"), out
        assert out.count("---") == 1
        publisher.send_signal(signal.SIGINT)
        publisher.wait(10)


@pytest.mark.ros
def test_echo_takes_the_durability_of_a_latched_publisher_outside_the_fleet(procs):
    """Not one of the fleet's known latched topics: transient-local must come from the
    discovered publisher."""
    procs.helper("latched", "/test/latched_map")
    code, out, err = run_echo(procs, "/test/latched_map", "--once")
    assert code == 0, err
    assert "resolution: 0.5" in out


@pytest.mark.ros
def test_echo_and_topics_take_the_fleets_namespace(procs):
    procs.helper("latched", "/fleet_a/fleet/map")
    code, out, err = run_echo(procs, "/fleet/map", "--namespace", "/fleet_a", "--once")
    assert code == 0, err
    assert "resolution: 0.5" in out
    proc = procs.cli("topics", "--namespace", "fleet_a")
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert out.splitlines() == ["/fleet_a/fleet/map [nav_msgs/msg/OccupancyGrid]"]


@pytest.mark.ros
def test_echo_matches_a_best_effort_publisher(procs):
    """A reliable subscription never matches a best-effort publisher: echo must take the
    publisher's reliability."""
    procs.helper("best-effort", "/test/chatter")
    code, out, err = run_echo(procs, "/test/chatter", "-n", "2")
    assert code == 0, err
    assert out.count("data: tick") == 2, out


@pytest.mark.ros
@pytest.mark.parametrize("signum, codes", [(signal.SIGTERM, (0, 143)), (signal.SIGINT, (0, 130))])
@pytest.mark.parametrize("state", ["receiving", "discovering"])
def test_echo_ends_cleanly_on_signal(procs, signum, codes, state):
    if state == "receiving":
        procs.helper("best-effort", "/test/chatter")
    proc = procs.cli("echo", "/test/chatter" if state == "receiving" else "/test/absent",
                     "--timeout", "60")
    if state == "receiving":
        wait_line(proc, "---", 40.0)  # it prints messages: it is in its receive loop
    else:
        # echo's handlers are installed (before that, while it still imports on a loaded
        # machine, a signal meets Python's defaults), then rclpy comes up and discovery runs
        assert wait_handlers(proc, 60.0), "echo never installed its signal handlers"
        time.sleep(2.0)
    sent = time.monotonic()
    proc.send_signal(signum)
    try:
        _, err = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        pytest.fail(f"echo still running 30 s after {signal.Signals(signum).name}")
    assert time.monotonic() - sent < 15.0  # not its --timeout of 60 s
    assert proc.returncode in codes, err
    assert "Traceback" not in err, err


@pytest.mark.ros
def test_echo_unknown_type_is_one_line_error(procs):
    code, out, err = run_echo(procs, "/test/x", "--type", "bogus")
    assert code == 2
    assert err.strip().splitlines() == [
        "mapf-fleet echo: message type 'bogus' is not of the form pkg/msg/Name"]


def test_choose_qos_follows_publishers():
    from rclpy.qos import DurabilityPolicy as D
    from rclpy.qos import ReliabilityPolicy as R

    from mapf_fleet.ros.echo import choose_qos, is_latched_topic

    def pub(reliability, durability):
        return SimpleNamespace(qos_profile=SimpleNamespace(reliability=reliability,
                                                           durability=durability))

    qos = choose_qos("/x", [pub(R.RELIABLE, D.TRANSIENT_LOCAL)])
    assert (qos.reliability, qos.durability) == (R.RELIABLE, D.TRANSIENT_LOCAL)
    qos = choose_qos("/x", [pub(R.RELIABLE, D.TRANSIENT_LOCAL), pub(R.BEST_EFFORT, D.VOLATILE)])
    assert (qos.reliability, qos.durability) == (R.BEST_EFFORT, D.VOLATILE)
    for topic in ("/fleet/map", "/fleet/outcome", "/robot_3/goal", "/robot_12/waypoint",
                  "/fleet_a/fleet/map"):
        assert is_latched_topic(topic), topic
        assert choose_qos(topic, []).durability == D.TRANSIENT_LOCAL
    for topic in ("/fleet/state", "/robot_3/pose", "/fleet/mapx", "/x/map"):
        assert not is_latched_topic(topic), topic
        assert choose_qos(topic, []).durability == D.VOLATILE


@pytest.mark.ros
def test_topics_waits_for_discovery_to_settle(procs):
    """Publishers appear over 4.5 s (a fleet coming up): every one must be listed."""
    trickle = procs.helper("trickle", "16", "0.3")
    proc = procs.cli("topics")
    out, err = proc.communicate(timeout=60)  # no upper bound on the time: --wait bounds it
    assert proc.returncode == 0, err
    listed = [line.split()[0] for line in out.splitlines() if line.startswith("/trickle/")]
    assert listed == [f"/trickle/t_{k:02d}" for k in range(16)], out
    assert all(line.endswith("[std_msgs/msg/String]") for line in out.splitlines()
               if line.startswith("/trickle/"))
    wait_line(trickle, "done", 10)


@pytest.mark.ros
def test_topics_is_bounded_by_wait_and_settles_early_on_a_quiet_graph(procs):
    procs.helper("latched", "/test/latched_map")
    proc = procs.cli("topics", "--wait", "30")
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "/test/latched_map [nav_msgs/msg/OccupancyGrid]" in out.splitlines()
    # settled before the 30 s bound: it says so when it is not (no wall-clock bound here: the
    # start of an rclpy process on a loaded 2-core machine takes seconds of its own)
    assert "may be incomplete" not in err, err
    # a graph that keeps changing: --wait bounds the command and says the list may be partial
    procs.helper("trickle", "100", "0.2")
    proc = procs.cli("topics", "--wait", "3")
    out, err = proc.communicate(timeout=60)  # the trickle lasts 20 s: bounded by --wait
    assert proc.returncode == 0, err
    assert "discovery still changing after 3 s" in err


@pytest.mark.ros
def test_topics_does_not_call_a_graph_without_other_nodes_settled(procs):
    """Under CI load the first participant arrived after the settle window and `topics` printed an
    empty list as if settled: a graph of only our own node waits for --wait and says so."""
    started = time.monotonic()
    proc = procs.cli("topics", "--wait", "5", "--settle", "1")
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert time.monotonic() - started >= 5.0
    assert "no other node discovered after 5 s" in err


@pytest.mark.ros
def test_echo_once_ends_at_its_timeout_on_a_silent_topic_and_names_a_wrong_type(ros_env):
    """A publisher that sends nothing: `echo --once --timeout 8` ends (exit 1) instead of
    waiting forever; a --type the topic's publishers do not offer is refused (exit 2)."""
    import rclpy
    from mapf_fleet_interfaces.msg import FleetProgress

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("silent_publisher", context=context)
    node.create_publisher(FleetProgress, "/fleet/progress", 10)
    try:
        cli = [sys.executable, "-m", "mapf_fleet.cli", "echo", "/fleet/progress"]
        started = time.monotonic()
        # the timeout covers discovering the publisher too: a loaded machine (the whole suite
        # on 2 cores) took over 3 s, so the topic was "not found"
        done = subprocess.run(cli + ["--once", "--timeout", "8"], env=ros_env,
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 1, done.stderr
        assert "0 of 1 message on /fleet/progress within 8 s" in done.stderr
        assert time.monotonic() - started < 60
        done = subprocess.run(cli + ["--once", "--timeout", "8", "--type", "std_msgs/msg/String"],
                              env=ros_env, capture_output=True, text=True, timeout=120)
        assert done.returncode == 2 and "has type mapf_fleet_interfaces/msg/FleetProgress" in \
            done.stderr, done.stderr
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_echo_with_a_type_and_no_publisher_says_so(ros_env):
    """--type skips waiting for the topic's type, not for its publisher: with none within
    --timeout, echo says there is no publisher (exit 1) instead of waiting for messages that
    cannot come and reporting "0 of 1 message"."""
    cli = [sys.executable, "-m", "mapf_fleet.cli", "echo", "/fleet/nobody_publishes", "--once",
           "--timeout", "2", "--type", "std_msgs/msg/String"]
    done = subprocess.run(cli, env=ros_env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert done.stderr == "mapf-fleet echo: no publisher of /fleet/nobody_publishes found " \
                          "within 2 s\n"
