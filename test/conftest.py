"""Shared test set-up: the ROS environment every test process needs, the `ros_env` fixture
that isolates each ROS test in its own DDS domain, and CI's rule on skips.

Under CI (`CI=true`, which .ci/run sets) a test that would skip because a file of ../shared
(the paper's text, the DHC test sets) is absent, or because the browser of the live-view test
(scripts/setup.sh installs Debian's chromium) is missing, fails instead: CI must run them all.

Several engineers (and CI) run ROS tests on the same machine at the same time, so a domain id is
reserved machine-wide with a lock file for the duration of a test, not just picked per process.
"""

from __future__ import annotations

import fcntl
import glob
import os
import re
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

# Make `python -m pytest` work without sourcing scripts/env.sh first: the venv is the ROS
# prefix, and nothing the tests start may talk beyond loopback. Set before any rclpy import so
# that subprocesses inherit it too.
os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

# ---- CI: what may not be skipped ---------------------------------------------------------------
SHARED = REPO.parent / "shared"
# The skip reasons of tests whose data lies in ../shared (paths as written in the tests).
SHARED_SKIP_RE = re.compile(r"/shared/|shared .*absent|test sets absent|not present")
# The skip reason of the live-view browser tests (headless_browser.require_browser).
BROWSER_SKIP_RE = re.compile(r"no headless browser")


def under_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


def must_not_skip(reason: str) -> bool:
    """Whether, under CI, a skip with this reason is a failure."""
    return bool(SHARED_SKIP_RE.search(reason) or BROWSER_SKIP_RE.search(reason))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if not (report.skipped and under_ci()) or hasattr(report, "wasxfail"):
        return
    reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
    if must_not_skip(reason):
        report.outcome = "failed"
        report.longrepr = (f"CI=true: this test may not skip ({reason}); ../shared is "
                           f"{SHARED} (exists: {SHARED.is_dir()}); the browser comes from "
                           "scripts/setup.sh (apt-get install chromium chromium-driver)")


# Domain ids 1..101 keep Fast DDS's port numbers valid on Linux; 0 is everyone's default.
DOMAIN_IDS = range(1, 102)
DOMAIN_LOCK_DIR = Path(os.environ.get("MAPF_FLEET_DOMAIN_LOCKS", "/tmp/mapf_fleet_ros_domains"))
# Shared-memory files younger than this may belong to a process that is still setting up.
STALE_SHM_AGE_S = 10.0


class RosTestEnv(dict):
    """What a ROS test needs: the environment for the processes it starts (this dict itself, so
    `subprocess.Popen(..., env=ros_env)` works), with its private `.domain_id`."""

    def __init__(self, domain_id: int, env: dict[str, str]):
        super().__init__(env)
        self.domain_id = domain_id

    @property
    def env(self) -> dict[str, str]:
        return self


def _reserve_domain_id() -> tuple[int, int]:
    """Lock and return (domain_id, lock_fd). The lock (flock) is released when the fd closes or
    the process dies, so a crashed test run never leaks a reservation."""
    DOMAIN_LOCK_DIR.mkdir(parents=True, exist_ok=True)
    start = os.getpid() % len(DOMAIN_IDS)  # spread concurrent runs over the range
    for k in range(len(DOMAIN_IDS)):
        domain_id = DOMAIN_IDS[(start + k) % len(DOMAIN_IDS)]
        fd = os.open(DOMAIN_LOCK_DIR / f"{domain_id}.lock", os.O_CREAT | os.O_RDWR, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        return domain_id, fd
    raise RuntimeError(f"all ROS domain ids {DOMAIN_IDS.start}..{DOMAIN_IDS.stop - 1} are in use")


def _shm_files_in_use() -> set[str]:
    """Every /dev/shm path some live process has mapped or open."""
    in_use: set[str] = set()
    for proc in glob.glob("/proc/[0-9]*"):
        try:
            with open(f"{proc}/maps") as maps:
                for line in maps:
                    idx = line.find("/dev/shm/")
                    if idx >= 0:
                        in_use.add(line[idx:].rstrip("\n").removesuffix(" (deleted)"))
            for fd in os.listdir(f"{proc}/fd"):
                target = os.readlink(f"{proc}/fd/{fd}")
                if target.startswith("/dev/shm/"):
                    in_use.add(target)
        except OSError:  # the process ended or is not ours to read
            continue
    return in_use


def cleanup_stale_fastdds_shm() -> int:
    """Remove Fast DDS shared-memory files that no live process uses (left by killed nodes).
    Files still mapped or open by anyone (another engineer's running fleet) are kept."""
    candidates = glob.glob("/dev/shm/fastrtps_*") + glob.glob("/dev/shm/sem.fastrtps_*")
    if not candidates:
        return 0
    in_use = _shm_files_in_use()
    now = time.time()
    removed = 0
    for path in candidates:
        try:
            if path in in_use or now - os.path.getmtime(path) < STALE_SHM_AGE_S:
                continue
            os.remove(path)
            removed += 1
        except OSError:
            continue
    return removed


@pytest.fixture
def ros_env(monkeypatch: pytest.MonkeyPatch) -> RosTestEnv:
    """A private ROS_DOMAIN_ID for this test (set in os.environ for in-process rclpy, and in
    `.env` for subprocesses), loopback-only discovery, and removal of stale Fast DDS
    shared-memory files before and after the test."""
    cleanup_stale_fastdds_shm()
    domain_id, lock_fd = _reserve_domain_id()
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain_id))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    try:
        yield RosTestEnv(domain_id, dict(os.environ))
    finally:
        os.close(lock_fd)
        cleanup_stale_fastdds_shm()


@pytest.fixture(autouse=True)
def _isolate_ros_tests(request: pytest.FixtureRequest) -> None:
    """Every test marked `ros` gets its own domain even if it does not ask for `ros_env`."""
    if request.node.get_closest_marker("ros") is not None:
        request.getfixturevalue("ros_env")
