"""Fixtures of the ROS fleet tests. The environment and the per-test ROS_DOMAIN_ID come from the
root `test/conftest.py` fixture `ros_env` (machine-wide locked domain ids, safe Fast DDS
shared-memory cleanup); this file only adds checkpoints with random weights (small preset)."""

from __future__ import annotations

import pytest


def _save(folder, algo: str, sensitive: bool) -> str:
    import torch

    from mapf_fleet.models.checkpoint import build_model, save_checkpoint
    from mapf_fleet.models.config import ModelConfig

    torch.manual_seed(7)
    model = build_model(ModelConfig.preset(algo, "small"))
    name = algo
    if sensitive:
        from mapf_fleet.models.synthetic import make_sensitive

        make_sensitive(model, seed=3)
        name = f"{algo}_sensitive"
    return str(save_checkpoint(folder / f"{name}.pt", model, {
        "alpha": 0.0, "curriculum": {}, "learner_steps": 0, "training_config": {}}))


@pytest.fixture(scope="session")
def checkpoints(tmp_path_factory):
    """{"dhc", "dcc"}: small random checkpoints; "dcc_sensitive": a DCC checkpoint whose weights
    (mapf_fleet.models.synthetic.make_sensitive) make its causal sets non-empty, so the robots
    really send requests and replies."""
    folder = tmp_path_factory.mktemp("checkpoints")
    paths = {algo: _save(folder, algo, False) for algo in ("dhc", "dcc")}
    paths["dcc_sensitive"] = _save(folder, "dcc", True)
    return paths


@pytest.fixture
def rclpy_context(ros_env):
    """rclpy initialised in this test process (the test's own domain, loopback: ros_env)."""
    import rclpy

    rclpy.init(args=["test"])
    try:
        yield rclpy
    finally:
        rclpy.try_shutdown()
