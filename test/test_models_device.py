"""`models.policy.resolve_device`: the one reading of a device name for the policy processes, the
evaluator and the trainers (auto is cuda only where torch sees one; cuda without one and unknown
names refused in one line)."""

from __future__ import annotations

import pytest
import torch

from mapf_fleet.models.policy import LearnedPolicy, resolve_device


def test_names_are_read_once_and_cuda_is_refused_without_a_cuda_device(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu") == resolve_device("cpu")
    for name in ("cuda", "cuda:1"):
        with pytest.raises(ValueError, match=rf"^device is {name}, but torch sees no CUDA device"):
            resolve_device(name)
    for name in ("tpu", "gpu", "", "cpu:x"):
        with pytest.raises(ValueError, match=r"^device must be auto, cpu, cuda or cuda:N, got"):
            resolve_device(name)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == torch.device("cuda")
    assert resolve_device("cuda:1") == torch.device("cuda", 1)


def test_a_learned_policy_runs_where_auto_says():
    from mapf_fleet.training.config import TrainConfig
    from mapf_fleet.training.modelio import build_model

    policy = LearnedPolicy(build_model(TrainConfig(algo="dhc")), "auto")
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert policy.device.type == expected
    assert next(policy.model.parameters()).device.type == expected


def test_the_evaluators_default_is_the_fleets_auto_and_bad_names_are_refused():
    import argparse

    from mapf_fleet.evaluation import cli, lifelong, render

    for parser in (cli.build_parser(), lifelong.build_parser(), render.build_parser()):
        device = next(a for a in parser._actions if a.dest == "device")
        assert device.default == "auto"  # what the policy processes' parameter device defaults to
        assert device.type("cpu") == "cpu"
        with pytest.raises(argparse.ArgumentTypeError,
                           match=r"^device must be auto, cpu, cuda or cuda:N, got 'tpu'"):
            device.type("tpu")
