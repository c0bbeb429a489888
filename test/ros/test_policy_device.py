"""The `device` parameter of the policy nodes (auto / cpu / cuda): resolved where the model is
loaded, cuda without a CUDA device refused in one line before anything starts (`up`)."""

from __future__ import annotations

import pytest
import torch

from mapf_fleet.ros import common, launcher


def test_auto_is_cuda_only_when_torch_sees_one(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert common.resolve_device("auto") == "cpu" and common.resolve_device("cpu") == "cpu"
    with pytest.raises(ValueError, match=r"^parameter device is cuda, but torch sees no CUDA "):
        common.resolve_device("cuda")
    with pytest.raises(ValueError, match="device must be one of auto, cpu, cuda, got 'tpu'"):
        common.resolve_device("tpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert common.resolve_device("auto") == "cuda" and common.resolve_device("cuda") == "cuda"


def test_the_policy_model_is_loaded_on_its_device(checkpoints):
    from mapf_fleet.ros.policy_node import load_policy_model

    model, _ = load_policy_model(checkpoints["dhc"], "cpu")
    assert next(model.parameters()).device.type == "cpu" and not model.training


def test_up_refuses_cuda_without_one_before_anything_starts(checkpoints, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(launcher.UpError, match="^parameter device is cuda, but torch sees no"):
        launcher.prepare(["--checkpoint", checkpoints["dhc"], "--device", "cuda"])
    _, plan, _ = launcher.prepare(["--checkpoint", checkpoints["dhc"], "--device", "cpu"])
    assert plan.device == "cpu"
