"""Run directory layout and atomic writes.

    RUN/config.yaml          the TrainConfig used (resume reads it back)
    RUN/train_state.pt       learner (model, target, optimizer), curricula, counters; rewritten
                             atomically every few minutes / N updates, so kill -9 loses little
    RUN/checkpoints/*.pt     model checkpoints (mapf_fleet.models.checkpoint format):
                             stage1.pt (end of stage 1), alpha_0.0.pt, alpha_0.1.pt, ... (each
                             alpha that passed the gate), final.pt (last weights)
    RUN/tb/                  TensorBoard scalars
    RUN/result.json          outcome: alpha*, passed alphas, stop reason, counters
    RUN/replay.npz           the replay's sequences and priorities, written atomically when the
                             run stops and every `replay_interval_seconds`: a resumed run
                             learns on the experience it had instead of a near-empty replay
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mapf_fleet.aliases import renamed_keys
from mapf_fleet.files import atomic_write

from .config import TrainConfig, config_from_dict, load_config

CONFIG_FILE = "config.yaml"
STATE_FILE = "train_state.pt"
RESULT_FILE = "result.json"
CHECKPOINT_DIR = "checkpoints"
TB_DIR = "tb"
REPLAY_FILE = "replay.npz"


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


def save_replay(run_dir: Path, state: dict[str, np.ndarray]) -> None:
    atomic_write(Path(run_dir) / REPLAY_FILE, lambda f: np.savez(f, **state))


def load_replay(run_dir: Path) -> dict[str, np.ndarray] | None:
    """The saved replay arrays, or None when the run has none; a damaged file raises a
    ValueError naming it."""
    path = Path(run_dir) / REPLAY_FILE
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise ValueError(f"{path}: not a readable replay file ({err})") from err


def earlier_overrides(run_dir: str | Path) -> dict:
    """The `--set` overrides of the run's earlier resumed sessions, merged in order (a later
    session's value wins)."""
    merged: dict = {}
    for session in load_state(Path(run_dir)).get("code_versions", []):
        merged.update(session.get("overrides") or {})
    return merged


def resumed_config(run_dir: str | Path) -> TrainConfig:
    """The config a resume continues with: config.yaml (the starting config) with the overrides
    of earlier resumed sessions applied, so a run goes on as it was left; a resume without --set
    does not silently return to the starting config."""
    run_dir = Path(run_dir)
    cfg = load_config(run_dir / CONFIG_FILE)
    earlier = renamed_keys(earlier_overrides(run_dir), str(run_dir / STATE_FILE), quiet=True)
    if earlier:
        cfg = config_from_dict({**cfg.to_dict(), **earlier},
                               source=f"{run_dir / STATE_FILE} (overrides of earlier sessions)")
    return cfg


def stage2_scheme(config: dict) -> str:
    """What stage 2 trains: the alpha curriculum, one fixed alpha, or nothing."""
    mode = config.get("alpha_mode", "curriculum")
    return f"fixed alpha {config.get('fixed_alpha')}" if mode == "fixed" else f"alpha_mode {mode}"
