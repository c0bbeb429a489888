"""`mapf-fleet train --export RUN --out FILE`: a checkpoint from a run's last saved state."""

from __future__ import annotations

from pathlib import Path

from . import run_state
from .run_state import resumed_config


def export_checkpoint(run_dir: str | Path, out: str | Path) -> tuple[Path, dict]:
    """Write the weights of RUN's last saved training state as a checkpoint file `out`, with
    the same metadata a curriculum checkpoint gets. Reads RUN only (the state file is written
    atomically), so it is safe while the run is still training."""
    from mapf_fleet.models.checkpoint import save_checkpoint

    run_dir = Path(run_dir)
    for name in (run_state.CONFIG_FILE, run_state.STATE_FILE):
        if not (run_dir / name).is_file():
            raise FileNotFoundError(f"{run_dir / name}: no such file (is {run_dir} a run directory?)")
    # constructing with resume=True only reads the run directory; training starts in run()
    from .trainer import Trainer

    trainer = Trainer(resumed_config(run_dir), run_dir, resume=True, restore_replay=False)
    meta = trainer._metadata()
    return save_checkpoint(out, trainer.learner.model, meta), meta
