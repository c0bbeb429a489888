"""DAgger runs side by side: `compare_runs` (a Markdown table of their held-out curves, the A/Bs)
and `plot_runs` (success per round as a PNG)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml

from mapf_fleet.files import atomic_write

from .config import DaggerConfigError
from .driver import CONFIG_FILE, CURVE_JSON


def _read_runs(run_dirs: list[str | Path]) -> list[tuple[Path, dict, list[dict]]]:
    """(run directory, its config, its held-out curve) of each DAgger run directory."""
    runs = []
    for run_dir in map(Path, run_dirs):
        curve_file, config_file = run_dir / CURVE_JSON, run_dir / CONFIG_FILE
        if not curve_file.is_file() or not config_file.is_file():
            raise DaggerConfigError(f"{run_dir}: not a DAgger run directory (no {CURVE_JSON} "
                                    f"or {CONFIG_FILE})")
        runs.append((run_dir, yaml.safe_load(config_file.read_text()) or {},
                     json.loads(curve_file.read_text())))
    return runs


def _heldout_keys(curves) -> list[str]:
    """The held-out settings ("dense21_48", ...) the curves' rows hold, in order of appearance."""
    return list(dict.fromkeys(k[:-len("_success")] for curve in curves for row in curve
                              for k in row if k.endswith("_success")))


def compare_runs(run_dirs: list[str | Path], last: int = 4) -> str:
    """A Markdown table of DAgger runs side by side (the A/Bs): per run its loss,
    observation, rounds, labels and CPU-hours, and per held-out setting the success (average
    steps) of plain PIBT, the init checkpoint, the last round, and the mean over the last `last`
    rounds (each round's check is `heldout_count` instances: the mean of several rounds is less
    noisy than any one round, though its rounds are different checkpoints)."""
    if last < 1:
        raise DaggerConfigError(f"--last must be >= 1, got {last}")
    runs = []
    for run_dir, config, curve in _read_runs(run_dirs):
        rounds = sorted((r for r in curve if r["policy"] == "dagger"), key=lambda r: r["round"])
        if not rounds:
            raise DaggerConfigError(f"{run_dir}: no round has finished its held-out check yet")
        runs.append((run_dir, config, curve, rounds))
    keys = _heldout_keys(curve for _, _, curve, _ in runs)

    def cell(rows: list[dict], key: str) -> str:
        have = [r for r in rows if f"{key}_success" in r]
        if not have:
            return ""
        success = float(np.mean([r[f"{key}_success"] for r in have]))
        steps = float(np.mean([r[f"{key}_steps"] for r in have]))
        return f"{success:.2f} ({steps:.0f})"

    lines = ["| run | loss | observation | rounds | labels | CPU-h | policy | "
             + " | ".join(f"{k} success (steps)" for k in keys) + " |",
             "|---|---|---|---:|---:|---:|---|" + "---:|" * len(keys)]
    for run_dir, config, curve, rounds in runs:
        final = rounds[-1]
        base = {r["policy"]: r for r in curve if r["round"] == -1}
        head = (f"| {run_dir.name} | {config.get('loss', '')} | "
                f"{config.get('observation') or 'init'} | {final['round'] + 1} | "
                f"{final['labels']:,} | {final['cpu_seconds'] / 3600:.2f} |")
        blank = "| | | | | | |"
        table = [("plain PIBT", [base["plain_pibt"]] if "plain_pibt" in base else []),
                 ("init", [base["init"]] if "init" in base else []),
                 (f"round {final['round']}", [final]),
                 (f"mean of rounds {rounds[-last:][0]['round']}-{final['round']}", rounds[-last:])]
        for i, (label, rows) in enumerate(table):
            lines.append(f"{head if i == 0 else blank} {label} | "
                         + " | ".join(cell(rows, k) for k in keys) + " |")
    return "\n".join(lines)


def plot_runs(run_dirs: list[str | Path], out: str | Path) -> Path:
    """The DAgger curves as a PNG: per held-out setting, each run's success per round (the init
    checkpoint at round -1) and plain PIBT's as a dashed line (the first run's)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = [(run_dir.name, curve) for run_dir, _, curve in _read_runs(run_dirs)]
    keys = _heldout_keys(curve for _, curve in curves)
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.4), squeeze=False)
    for ax, key in zip(axes[0], keys):
        for name, curve in curves:
            rows = sorted((r for r in curve if r["policy"] in ("init", "dagger")
                           and f"{key}_success" in r), key=lambda r: r["round"])
            ax.plot([r["round"] for r in rows], [r[f"{key}_success"] for r in rows],
                    marker="o", ms=3, label=name)
        base = [r for r in curves[0][1] if r["policy"] == "plain_pibt" and f"{key}_success" in r]
        if base:
            ax.axhline(base[0][f"{key}_success"], color="k", ls="--", lw=1, label="plain PIBT")
        ax.set_title(key)
        ax.set_xlabel("round (-1: init)")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("held-out success")
    axes[0][-1].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    out = Path(out)
    atomic_write(out, lambda f: fig.savefig(f, format="png", dpi=110))
    plt.close(fig)
    return out


