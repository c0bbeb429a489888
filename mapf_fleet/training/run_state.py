"""Run directory layout and atomic writes.

    RUN/config.yaml          the TrainConfig used (resume reads it back)
    RUN/train_state.pt       learner (model, target, optimizer), curricula, counters; rewritten
                             atomically every few minutes / N updates, so kill -9 loses little
    RUN/checkpoints/*.pt     model checkpoints (mapf_fleet.models.checkpoint format):
                             stage1.pt (end of stage 1), alpha_0.0.pt, alpha_0.1.pt, ... (each
                             alpha that passed the gate), final.pt (last weights)
    RUN/tb/                  TensorBoard scalars
    RUN/result.json          outcome: alpha*, passed alphas, stop reason, counters
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from mapf_fleet.files import atomic_write

CONFIG_FILE = "config.yaml"
STATE_FILE = "train_state.pt"
RESULT_FILE = "result.json"
CHECKPOINT_DIR = "checkpoints"
TB_DIR = "tb"


def save_state(run_dir: Path, state: dict[str, Any]) -> None:
    atomic_write(Path(run_dir) / STATE_FILE, lambda f: torch.save(state, f))


def load_state(run_dir: Path) -> dict[str, Any]:
    path = Path(run_dir) / STATE_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no training state to resume from")
    return torch.load(path, map_location="cpu", weights_only=True)


def write_result(run_dir: Path, result: dict[str, Any]) -> None:
    atomic_write(Path(run_dir) / RESULT_FILE,
                  lambda f: f.write(json.dumps(result, indent=2).encode()))


def alpha_checkpoint_name(alpha: float) -> str:
    return f"alpha_{alpha:.1f}.pt" if abs(alpha * 10 - round(alpha * 10)) < 1e-9 \
        else f"alpha_{alpha:g}.pt"
