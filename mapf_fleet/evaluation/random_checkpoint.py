"""Checkpoints with random weights, for timing the evaluator and for its tests (a learned
checkpoint gives the same code path, only better numbers)."""

from __future__ import annotations

from pathlib import Path


def save_random_checkpoint(path: str | Path, algo: str = "dhc", preset: str = "small", seed: int = 0) -> Path:
    """Write a `preset` ("paper" or "small") `algo` network with seeded random weights."""
    import torch

    from mapf_fleet.models.checkpoint import build_model, save_checkpoint
    from mapf_fleet.models.config import ModelConfig

    torch.manual_seed(seed)
    model = build_model(ModelConfig.preset(algo, preset))
    metadata = {
        "alpha": 0.0,
        "curriculum": {"note": "untrained: random weights"},
        "learner_steps": 0,
        "training_config": {"preset": preset, "seed": seed},
    }
    return save_checkpoint(path, model, metadata)
