"""`mapf-fleet card`: a checkpoint's model card in Markdown.

    mapf-fleet card --checkpoint models/X.pt --eval X_eval.json [--run-dir RUN]
        --out models/X.md [--curves models/X_curves.png]

Every number of the card comes from one of these files: the checkpoint's metadata, the JSON of
`mapf-fleet evaluate` (which records its own command line, so the card can show how to re-run
it), the run directory of the trainer (config.yaml, result.json, train_state.pt, tb/) and the
paper's tables (`paper_results`). Inputs that do not belong together (an evaluation of another
checkpoint, a run directory of another algorithm or network) raise `CardError`.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import hashlib
import json
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mapf_fleet import paths

from . import paper_results
from .paper_results import BASELINE, CURRICULUM, FIXED

# TensorBoard tags written by mapf_fleet.training.trainer (Trainer._write_scalars).
TAG_GATE_SUCCESS = "curriculum/gate_success_rate"
TAG_AGENTS = "curriculum/num_agents"
TAG_MAP_SIZE = "curriculum/map_size"
TAG_ALPHA = "curriculum/alpha"
TAG_LOSS = "learner/loss"
CURVE_TAGS = (TAG_GATE_SUCCESS, TAG_AGENTS, TAG_MAP_SIZE, TAG_ALPHA, TAG_LOSS)
# The paper's tables: (summary field, title, format), as mapf_fleet.evaluation.report prints them.
CARD_METRICS = (("success_rate", "Success rate ↑", "{:.3f}"), ("average_steps", "Average time steps ↓", "{:.2f}"))
REPO_ROOT = paths.SOURCE_ROOT  # paths given by the user are shown relative to a checkout


class CardError(ValueError):
    """A card input is missing, malformed or belongs to another checkpoint; names the file."""


# ---- inputs -------------------------------------------------------------------------------------


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def load_evaluation(path: str | Path) -> dict:
    """The JSON of `mapf-fleet evaluate --json`, with its structure checked."""
    path = Path(path)
    if not path.is_file():
        raise CardError(f"--eval {path}: no such file")
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CardError(f"--eval {path}: not a JSON file: {exc}") from exc
    if not isinstance(data, dict) or not isinstance(data.get("metadata"), dict) \
            or not isinstance(data.get("results"), list):
        raise CardError(f"--eval {path}: expected the JSON of `mapf-fleet evaluate --json` "
                        "(keys 'metadata' and 'results')")
    for index, row in enumerate(data["results"]):
        for key in ("policy", "map", "agents", "max_steps", "success_rate", "average_steps"):
            if not isinstance(row, dict) or key not in row:
                raise CardError(f"--eval {path}: results[{index}]: field {key!r} missing")
    if not isinstance(data["metadata"].get("policies"), list):
        raise CardError(f"--eval {path}: field metadata.policies missing (evaluation JSON too old?)")
    return data


class EvalFiles(tuple):
    """Several evaluation JSONs read as one (their paths print as a comma-separated list)."""

    def __str__(self) -> str:
        return ", ".join(str(p) for p in self)

    @property
    def name(self) -> str:
        return ", ".join(Path(p).name for p in self)


def load_evaluations(paths) -> tuple[dict, EvalFiles]:
    """One or more `mapf-fleet evaluate --json` files as one evaluation: the policies and rows
    of all (a row measured in several files, e.g. a reference, is taken from the first), each
    file's metadata kept under "runs" for the re-run commands. A policy name that stands for
    different checkpoint files in two of them is refused."""
    paths = EvalFiles(Path(p) for p in ([paths] if isinstance(paths, (str, Path)) else paths))
    if not paths:
        raise CardError("--eval: give at least one evaluation JSON")
    loaded = [(path, load_evaluation(path)) for path in paths]
    policies: dict[str, tuple[dict, Path]] = {}
    results, seen = [], set()
    for path, data in loaded:
        for entry in data["metadata"]["policies"]:
            name = entry.get("name")
            if name in policies:
                first, where = policies[name]
                if first.get("kind") == "checkpoint" and first.get("path") != entry.get("path"):
                    raise CardError(f"--eval: policy {name!r} is {first.get('path')} in {where} but "
                                    f"{entry.get('path')} in {path}; rename one checkpoint file")
            else:
                policies[name] = (entry, path)
        for row in data["results"]:
            key = (row["policy"], row["map"], int(row["agents"]))
            if key not in seen:
                seen.add(key)
                results.append(row)
    metadata = dict(loaded[0][1]["metadata"], policies=[e for e, _ in policies.values()])
    return {"metadata": metadata, "results": results,
            "runs": [(path, data["metadata"]) for path, data in loaded]}, paths


def match_policy(evaluation: dict, checkpoint: Path, eval_path: Path) -> str:
    """The row label under which `evaluation` holds `checkpoint`.

    A policy entry matches when its path is the same file as `checkpoint`, or a file with the
    same bytes, or (the path being relative to a directory we cannot know) has the same file
    name. Anything else is an evaluation of another checkpoint."""
    entries = [p for p in evaluation["metadata"]["policies"] if p.get("kind") == "checkpoint"]
    # the checkpoint's own row is its unshielded one; its shielded rows (`--shield pibt`, label
    # "<name> +PIBT...") are shown beside it by evaluation_section
    entries.sort(key=lambda p: p.get("shield", "none") not in (None, "none"))
    if not entries:
        raise CardError(f"--eval {eval_path}: evaluates no checkpoint (only references)")
    own_hash = None
    for entry in entries:
        other = Path(entry.get("path") or "")
        if other.is_file():
            if os.path.samefile(other, checkpoint):
                return entry["name"]
            own_hash = own_hash or _sha256(checkpoint)
            if _sha256(other) == own_hash:
                return entry["name"]
    # By name only when the recorded path does not exist here (evaluated from another directory):
    # an existing file with other bytes is another (or an older) checkpoint.
    same_name = [e for e in entries if Path(e.get("path") or "").name == checkpoint.name
                 and not Path(e.get("path") or "").is_file()]
    if len(same_name) == 1:
        return same_name[0]["name"]
    found = ", ".join(str(e.get("path")) for e in entries)
    raise CardError(f"--eval {eval_path}: evaluates checkpoint(s) {found}, not {checkpoint}; "
                    f"run `mapf-fleet evaluate --checkpoint {checkpoint} --json ...` first")


@dataclass
class RunInfo:
    """What the card uses of a trainer's run directory."""

    path: Path
    config: dict | None = None  # config.yaml
    result: dict | None = None  # result.json
    state_counters: dict | None = None  # train_state.pt "counters"
    state_updates: int | None = None
    checkpoint_in_run: str | None = None  # RUN/checkpoints/<name> with the same bytes
    tb_dir: Path | None = None
    notes: list[str] = field(default_factory=list)


def read_run_dir(run_dir: str | Path, checkpoint: Path, metadata: dict) -> RunInfo:
    """Read RUN's files and check that they belong to `checkpoint`."""
    import yaml

    run = RunInfo(Path(run_dir))
    if not run.path.is_dir():
        raise CardError(f"--run-dir {run.path}: no such directory")
    config_path = run.path / "config.yaml"
    if config_path.is_file():
        try:
            run.config = yaml.safe_load(config_path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise CardError(f"{config_path}: invalid YAML: {exc}") from exc
        _check_run_matches(run.config, metadata, config_path)
    result_path = run.path / "result.json"
    if result_path.is_file():
        try:
            run.result = json.loads(result_path.read_text())
        except json.JSONDecodeError as exc:
            raise CardError(f"{result_path}: not JSON: {exc}") from exc
    state_path = run.path / "train_state.pt"
    if state_path.is_file():
        import torch

        try:
            state = torch.load(state_path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - a torn or foreign file: say so, go on without it
            run.notes.append(f"{state_path.name} unreadable ({type(exc).__name__}); not used")
        else:
            run.state_counters = dict(state.get("counters") or {})
            learner = state.get("learner") or {}
            if isinstance(learner, dict) and isinstance(learner.get("updates"), int):
                run.state_updates = learner["updates"]
    if run.config is None and run.result is None and run.state_counters is None:
        raise CardError(f"--run-dir {run.path}: none of config.yaml, result.json, train_state.pt: "
                        "not a training run directory")
    own_hash = _sha256(checkpoint)
    for candidate in sorted((run.path / "checkpoints").glob("*.pt")):
        if _sha256(candidate) == own_hash:
            run.checkpoint_in_run = candidate.name
            break
    if (run.path / "tb").is_dir():
        run.tb_dir = run.path / "tb"
    return run


def _check_run_matches(config: dict, metadata: dict, where: Path) -> None:
    """The run's algorithm, network and seed must be the checkpoint's."""
    trained = metadata.get("training_config") or {}
    algo = config.get("algo")
    if algo is not None and algo != metadata["algorithm"]:
        raise CardError(f"{where}: algo {algo!r}, but the checkpoint is {metadata['algorithm']!r}: "
                        "the run directory belongs to another checkpoint")
    for key in ("model_preset", "model_overrides", "seed"):
        if key in config and key in trained and config[key] != trained[key]:
            raise CardError(f"{where}: {key} {config[key]!r}, but the checkpoint was trained with "
                            f"{trained[key]!r}: the run directory belongs to another checkpoint")
    preset = config.get("model_preset")
    if preset is not None:
        from mapf_fleet.models.config import ModelConfig

        try:
            expected = ModelConfig.preset(metadata["algorithm"], preset, **(config.get("model_overrides") or {}))
        except (TypeError, ValueError):
            return
        if expected.to_dict() != dict(metadata["model_config"]):
            raise CardError(f"{where}: model_preset {preset!r} builds another network than the "
                            "checkpoint's model_config: the run directory belongs to another checkpoint")


# ---- what the checkpoint is ---------------------------------------------------------------------


def model_summary(model, metadata: dict) -> dict:
    """Preset name (or "custom") and parameter count."""
    from mapf_fleet.models.config import PRESETS, ModelConfig

    config = dict(metadata["model_config"])
    preset = "custom"
    for name in PRESETS:
        if ModelConfig.preset(metadata["algorithm"], name).to_dict() == config:
            preset = name
    return {"preset": preset, "parameters": sum(p.numel() for p in model.parameters())}


def training_config_diff(training_config: dict) -> tuple[list[tuple[str, Any, Any]], str | None, str | None]:
    """(fields that differ from the paper's recipe for the algorithm as (name, value, paper value),
    the closest config file of config/training/ and how it differs), or ([], None, None) when the
    training config is not a TrainConfig."""
    try:
        from mapf_fleet.training.config import TrainConfigError, config_from_dict, load_config
    except ImportError:
        return [], None, None
    try:
        config = config_from_dict(dict(training_config), source="checkpoint training_config").to_dict()
        paper = config_from_dict({"preset": config["algo"]}, source="paper preset").to_dict()
    except (TrainConfigError, KeyError, TypeError):
        return [], None, None
    diff = [(k, v, paper.get(k)) for k, v in config.items() if paper.get(k) != v]
    best, best_diff = None, None
    for path in sorted(paths.data_path("config", "training").glob("*.yaml")):
        try:
            shipped = load_config(path).to_dict()
        except (TrainConfigError, OSError):
            continue
        differs = [k for k in config if shipped.get(k) != config[k]]
        if best_diff is None or len(differs) < len(best_diff):
            best, best_diff = path, differs
    if best is None:
        return diff, None, None
    note = "identical" if not best_diff else "differs in " + ", ".join(f"`{k}`" for k in best_diff)
    return diff, f"config/training/{best.name}", note


@dataclass(frozen=True)
class Compute:
    wall_seconds: float
    cpus: int | None
    source: str  # which file the wall time came from
    how: str  # the CPU count's origin
    measured_cpu_seconds: float | None = None  # counters.cpu_seconds: process CPU time measured
    measured_from_elapsed: float = 0.0  # the run's wall time before the trainer measured it

    @property
    def cpu_hours(self) -> float | None:
        return None if self.cpus is None else self.wall_seconds * self.cpus / 3600.0


def compute_spent(run: RunInfo | None, metadata: dict) -> Compute | None:
    """Wall time (summed over resumed sessions by the trainer's counters.elapsed_seconds) x the
    CPUs the run reserved, and the measured CPU time. A checkpoint holding the run's counters of
    its own moment (`extra.counters`, written by the trainer since they were added) is measured
    up to itself; otherwise the whole run: the latest of result.json and train_state.pt wins, and
    a checkpoint's `extra.elapsed_seconds` is used without a run dir."""
    extra = metadata.get("extra") or {}
    own = extra.get("counters")
    if isinstance(own, dict) and _is_number(own.get("elapsed_seconds")):
        # checkpoints the trainer writes now carry the run's counters of that moment
        return _compute_from(own, CHECKPOINT_POINT, run, metadata)
    candidates = []
    if run is not None:
        if run.result and isinstance(run.result.get("counters"), dict):
            candidates.append((run.result["counters"], "result.json counters.elapsed_seconds"))
        if run.state_counters:
            candidates.append((run.state_counters, "train_state.pt counters.elapsed_seconds"))
    candidates.append((extra, "checkpoint metadata extra.elapsed_seconds"))
    candidates = [(c, s) for c, s in candidates if _is_number(c.get("elapsed_seconds"))]
    if not candidates:
        return None
    counters, source = max(candidates, key=lambda c: float(c[0]["elapsed_seconds"]))
    return _compute_from(counters, source, run, metadata)


CHECKPOINT_POINT = "checkpoint metadata extra.counters, i.e. the run when this checkpoint was written"


def _compute_from(counters: dict, source: str, run: RunInfo | None, metadata: dict) -> Compute:
    wall = float(counters["elapsed_seconds"])
    measured = (float(counters["cpu_seconds"]) if _is_number(counters.get("cpu_seconds")) else None,
                float(counters.get("cpu_measured_from_elapsed_seconds") or 0.0))
    uncounted = uncounted_warm_start_seconds(run)
    if uncounted:
        wall += uncounted
        if measured[0] is not None:  # that warm start came before the CPU measurement began
            measured = (measured[0], measured[1] + uncounted)
        source += (f" + {uncounted:.0f} s of demonstration warm start that the trainer did not yet "
                   "count (runs started before it did: from the tb event file's creation to the "
                   "last demo/loss scalar)")
    config = (run.config if run and run.config else None) or metadata.get("training_config") or {}
    if config.get("ray_address"):
        cpus, how = None, "an external Ray cluster (ray_address): CPUs unknown"
    elif config.get("use_ray", True) and isinstance(config.get("num_cpus"), int):
        cpus, how = config["num_cpus"], "`num_cpus` of the local Ray (training config)"
    elif config.get("use_ray") is False and isinstance(config.get("learner_threads"), int):
        cpus, how = config["learner_threads"], "in-process actors (use_ray false): the learner's `learner_threads`"
    else:
        cpus, how = None, "the training config names no CPU count"
    return Compute(wall, cpus, source, how, *measured)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def uncounted_warm_start_seconds(run: RunInfo | None) -> float:
    """Runs begun before the trainer counted its demonstration warm start in elapsed_seconds
    but which logged demo/ scalars: the warm start's wall time, from the first event of the event
    file holding demo/loss to its last demo/loss scalar of the warm start (step <=
    demo_pretrain_updates; later ones are interleaved demo updates). Counted already when the
    run's `demo_seconds` (all warm starts and demonstration refreshes the trainer timed) holds at
    least 90 % of it; a run that began uncounted and got `demo_seconds` in a later session only
    holds its refreshes there."""
    if run is None or run.tb_dir is None:
        return 0.0
    counters = run.state_counters or (run.result or {}).get("counters") or {}
    if not counters.get("demo_pretrained"):
        return 0.0
    counted = float(counters.get("demo_seconds") or 0.0)
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    for path in sorted(run.tb_dir.glob("events.out.tfevents.*")):
        accumulator = EventAccumulator(str(path), size_guidance={"scalars": 0})
        accumulator.Reload()
        if "demo/loss" in accumulator.Tags().get("scalars", []):
            limit = int((run.config or {}).get("demo_pretrain_updates") or 0)
            warm = [e for e in accumulator.Scalars("demo/loss") if not limit or e.step <= limit]
            if warm:
                seconds = float(warm[-1].wall_time - accumulator.FirstEventTimestamp())
                return 0.0 if counted >= 0.9 * seconds else seconds
    return 0.0


# ---- curves -------------------------------------------------------------------------------------


def read_scalars(tb_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar of RUN/tb as tag -> [(step, value)] (all event files, in order)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    accumulator = EventAccumulator(str(tb_dir), size_guidance={"scalars": 0})
    accumulator.Reload()
    return {tag: [(e.step, e.value) for e in accumulator.Scalars(tag)]
            for tag in accumulator.Tags().get("scalars", [])}


def scalars_up_to(scalars: dict[str, list[tuple[int, float]]], learner_steps: int
                  ) -> tuple[dict[str, list[tuple[int, float]]], int | None]:
    """The scalars logged up to a checkpoint's learner update, and the last update the run logged
    beyond it (None if none): the card of an intermediate checkpoint (a warm start, an alpha of
    stage 2) shows the training that made it, not what the run did afterwards."""
    later = [step for points in scalars.values() for step, _ in points if step > learner_steps]
    kept = {tag: [(step, value) for step, value in points if step <= learner_steps]
            for tag, points in scalars.items()}
    return {tag: points for tag, points in kept.items() if points}, (max(later) if later else None)


def plot_curves(scalars: dict[str, list[tuple[int, float]]], out: Path, title: str) -> list[str]:
    """PNG of the curves (success rate, curriculum setting, alpha, loss) against learner
    updates; returns the tags plotted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    plotted = []

    def line(ax, tag, label, **style):
        points = scalars.get(tag)
        if not points:
            return False
        ax.plot([p[0] for p in points], [p[1] for p in points], label=label, **style)
        plotted.append(tag)
        return True

    panels = [
        (axes[0, 0], "success rate of the gating actors", [(TAG_GATE_SUCCESS, "gate success rate", {})]),
        (axes[0, 1], "curriculum setting", [(TAG_AGENTS, "agents", {"drawstyle": "steps-post"})]),
        (axes[1, 0], "alpha (cooperation coefficient)", [(TAG_ALPHA, "alpha", {"drawstyle": "steps-post"})]),
        (axes[1, 1], "learner loss", [(TAG_LOSS, "loss", {})]),
    ]
    for ax, name, tags in panels:
        drawn = [line(ax, tag, label, **style) for tag, label, style in tags]
        if ax is axes[0, 1] and scalars.get(TAG_MAP_SIZE):
            twin = ax.twinx()
            line(twin, TAG_MAP_SIZE, "map size", color="tab:orange", linestyle="--", drawstyle="steps-post")
            twin.set_ylabel("map size (cells per side)", color="tab:orange")
            drawn.append(True)
        if not any(drawn):
            ax.text(0.5, 0.5, "not logged", ha="center", va="center", transform=ax.transAxes)
        ax.set_title(name)
        ax.set_xlabel("learner updates")
        ax.grid(alpha=0.3)
    if scalars.get(TAG_GATE_SUCCESS):
        axes[0, 0].set_ylim(-0.02, 1.02)
    loss = scalars.get(TAG_LOSS) or []
    if loss and all(v > 0 for _, v in loss):
        axes[1, 1].set_yscale("log")
    axes[0, 1].set_ylabel("agents")
    fig.suptitle(title)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return plotted


# ---- the card -----------------------------------------------------------------------------------


def _fmt(value, pattern: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return pattern.format(value)


def _episode_count(row: dict) -> int:
    episodes = row.get("episodes")
    return len(episodes) if isinstance(episodes, list) else int(episodes or 0)


def _map_size(map_name: str) -> int | None:
    parts = map_name.split("x")
    if len(parts) == 2 and parts[0] == parts[1] and parts[0].isdigit():
        return int(parts[0])
    return None


def evaluation_section(evaluation: dict, policy: str, metadata: dict, eval_path: Path) -> list[str]:
    """Per map: the measured rows of this checkpoint and of the references, the paper's rows of
    the same algorithm below them."""
    references = [p["name"] for p in evaluation["metadata"]["policies"] if p.get("kind") != "checkpoint"]
    # the same checkpoint under the coordination layer (rows "<policy> +PIBT", "+PIBT(mode)")
    shielded = [p["name"] for p in evaluation["metadata"]["policies"] if p.get("kind") == "checkpoint"
                and p["name"].startswith(f"{policy} +PIBT")]
    rows = [r for r in evaluation["results"] if r["policy"] in (policy, *shielded, *references)]
    if not any(r["policy"] == policy for r in rows):
        raise CardError(f"--eval {eval_path}: metadata lists {policy!r} but results hold no row of it")
    algorithm, alpha = metadata["algorithm"], float(metadata["alpha"])
    fixed = (metadata.get("training_config") or {}).get("alpha_mode") == "fixed"
    lines = []
    for map_name in dict.fromkeys(r["map"] for r in rows):
        mine = [r for r in rows if r["map"] == map_name]
        agents = sorted({int(r["agents"]) for r in mine})
        limits = "/".join(str(v) for v in sorted({r["max_steps"] for r in mine}))
        counts = "/".join(str(v) for v in sorted({_episode_count(r) for r in mine if r["policy"] == policy}))
        sources = "; ".join(sorted({str(r.get("source", "?")) for r in mine}))
        size = _map_size(map_name)
        paper = []
        if size in paper_results.TABLE_BY_SIZE:
            methods = (BASELINE, CURRICULUM, FIXED) if fixed else (BASELINE, CURRICULUM)
            paper = paper_results.paper_rows(algorithm, size, methods)
        lines.append(f"### {map_name}\n")
        lines.append(f"Measured on {counts} instances per scenario, limit {limits} steps; instances: {sources}.")
        if paper:
            tables = ", ".join(dict.fromkeys(r.table for r in paper))
            lines.append(f"Paper rows ({tables}) are the paper's own numbers on 200 instances per scenario "
                         "(its instances, its training compute), quoted for comparison.")
        lines.append("")
        for metric, title, pattern in CARD_METRICS:
            cell = {(r["policy"], int(r["agents"])): r[metric] for r in mine}
            lines.append(f"| {title} | " + " | ".join(str(n) for n in agents) + " |")
            lines.append("|---|" + "---:|" * len(agents))
            own = [policy, *[n for n in shielded if any(r["policy"] == n for r in mine)]]
            for name in [*own, *[n for n in references if any(r["policy"] == n for r in mine)]]:
                label = (f"**{name}** (this checkpoint)" if name == policy else
                         f"**{name}** (this checkpoint under the PIBT shield)" if name in own else
                         f"{name} (reference)")
                lines.append(f"| {label} | " + " | ".join(_fmt(cell.get((name, n)), pattern) for n in agents) + " |")
            for row in paper:
                values = getattr(row, metric)
                same_method = row.method == BASELINE or (row.method == FIXED) == fixed
                mark = " ◀ same α" if abs(row.alpha - alpha) < 1e-9 and same_method else ""
                lines.append(f"| paper {row.table}: {row.label}{mark} | "
                             + " | ".join(_fmt(values.get(n), pattern) for n in agents) + " |")
            lines.append("")
        lines += _against_heuristic(mine, policy, agents)
        # the rows under a shield (the checkpoint's own row too when the JSON ran it shielded)
        for name in [*([policy] if "+PIBT" in policy else []), *shielded]:
            lines += _against_plain_pibt(mine, name, agents)
    return lines


RECIPES = {"none": "paper recipe (no demonstrations)",
           "planner": "DQfD warm start on LaCAM plans",
           "heuristic": "DQfD warm start on the heuristic policy"}


def _hours(value: float | None) -> str:
    return "not recorded" if value is None else f"{value / 3600:.2f}"


def comparison_section(evaluation: dict, policy: str, metadata: dict, eval_path: Path,
                       others: list[tuple[Path, dict]], run: RunInfo | None) -> list[str]:
    """This checkpoint beside other checkpoints measured in the same evaluation JSON(s) (issue 8
    item 4: the warm start beside the paper's recipe): how each was trained, the compute spent up
    to it and its success rates. `others`: (checkpoint, its metadata, its RunInfo or None)."""
    entries = [(policy, metadata, compute_spent(run, metadata))]
    for path, meta, other_run in others:
        name = match_policy(evaluation, path, eval_path)
        if name == policy:
            raise CardError(f"--compare {path}: is the card's own checkpoint")
        entries.append((name, meta, compute_spent(other_run, meta)))
    lines = ["## Side by side", "",
             f"Checkpoints measured with the same protocol (`{eval_path.name}`); compute up to each "
             "checkpoint, read from its metadata (measured = process CPU time of the trainer and its "
             "actors; reserved = wall time x CPUs of the run).", "",
             "| checkpoint | algorithm | training | setting reached | alpha | learner steps "
             "| CPU-h measured | CPU-h reserved |", "|---|---|---|---|---:|---:|---:|---:|"]
    for name, meta, compute in entries:
        config = meta.get("training_config") or {}
        setting = (meta.get("curriculum") or {}).get("setting") or ["?", "?"]
        measured = None if compute is None else compute.measured_cpu_seconds
        if compute is not None and compute.measured_from_elapsed > 0 and measured is not None:
            measured_text = f"{measured / 3600:.2f} (last {(compute.wall_seconds - compute.measured_from_elapsed) / 3600:.2f} h of wall time)"
        else:
            measured_text = _hours(measured)
        reserved = None if compute is None or compute.cpu_hours is None else compute.cpu_hours * 3600
        label = f"**{name}** (this checkpoint)" if name == policy else name
        lines.append(f"| {label} | {meta.get('algorithm', '?').upper()} "
                     f"| {RECIPES.get(config.get('demo_source', 'none'), config.get('demo_source'))} "
                     f"| {setting[0]} agents on {setting[1]}x{setting[1]} | {float(meta.get('alpha', 0)):g} "
                     f"| {int(meta.get('learner_steps', 0)):,} | {measured_text} | {_hours(reserved)} |")
    lines.append("")
    names = [e[0] for e in entries]
    rows = [r for r in evaluation["results"] if r["policy"] in names]
    for map_name in dict.fromkeys(r["map"] for r in rows):
        mine = [r for r in rows if r["map"] == map_name]
        agents = sorted({int(r["agents"]) for r in mine})
        cell = {(r["policy"], int(r["agents"])): r["success_rate"] for r in mine}
        lines.append(f"| Success rate ↑, {map_name} | " + " | ".join(str(n) for n in agents) + " |")
        lines.append("|---|" + "---:|" * len(agents))
        for name in names:
            lines.append(f"| {name} | " + " | ".join(_fmt(cell.get((name, n)), "{:.3f}") for n in agents) + " |")
        lines.append("")
    return lines


def _against_heuristic(rows: list[dict], policy: str, agents: list[int]) -> list[str]:
    """Where this checkpoint's success rate is above the non-learned decentralized policy's
    (issue 8's first target), from the measured rows only."""
    mine = {int(r["agents"]): r["success_rate"] for r in rows if r["policy"] == policy}
    floor = {int(r["agents"]): r["success_rate"] for r in rows if r["policy"] == "heuristic"}
    shared = [n for n in agents if n in mine and n in floor]
    if not shared:
        return []
    above = [n for n in shared if mine[n] > floor[n]]
    verdict = "at every agent count" if len(above) == len(shared) else (
        "at " + ", ".join(map(str, above)) + " agents only" if above else "at no agent count")
    return [f"Success rate above the non-learned heuristic: {verdict} "
            f"(of {', '.join(map(str, shared))}).", ""]


PLAIN_PIBT = "heuristic +PIBT"  # the evaluator's row of the heuristic's ranking under the shield


def _against_plain_pibt(rows: list[dict], name: str, agents: list[int]) -> list[str]:
    """Where this checkpoint under the shield is at least plain PIBT (the non-learned ranking
    under the same shield; issue 18's first target), in success rate and in average steps, from
    the measured rows only."""
    mine = {int(r["agents"]): r for r in rows if r["policy"] == name}
    pibt = {int(r["agents"]): r for r in rows if r["policy"] == PLAIN_PIBT}
    shared = [n for n in agents if n in mine and n in pibt]
    if not shared:
        return []

    def verdict(ok: list[int]) -> str:
        if len(ok) == len(shared):
            return "at every agent count"
        return ("at " + ", ".join(map(str, ok)) + " agents only") if ok else "at no agent count"

    success = [n for n in shared if mine[n]["success_rate"] >= pibt[n]["success_rate"]]
    steps = [n for n in shared if mine[n]["average_steps"] <= pibt[n]["average_steps"]]
    return [f"{name} against plain PIBT ({PLAIN_PIBT}, same shield): success rate at least "
            f"PIBT's {verdict(success)}, average steps at most PIBT's {verdict(steps)} "
            f"(of {', '.join(map(str, shared))}).", ""]


def _yaml_block(data: dict) -> str:
    import yaml

    return "```yaml\n" + yaml.safe_dump(data, sort_keys=False).rstrip() + "\n```"


def _relative(target: Path, start: Path) -> str:
    return Path(os.path.relpath(target.resolve(), start.resolve())).as_posix()


def evaluation_block(evaluation: dict, policy: str, metadata: dict, eval_path, title: str) -> list[str]:
    """The card's evaluation section: the re-run commands of the JSON(s), then the tables."""
    runs = evaluation["runs"]
    lines = [f"## {title}", "",
              "Re-run the numbers below with (from the directory it was run in):", ""]
    for path, meta in runs:
        if len(runs) > 1:
            lines += [f"`{path.name}`:", ""]
        lines += [f"```\n{meta.get('command', '(the evaluation JSON does not record its command)')}\n```", ""]
        info = []
        if meta.get("protocol_file"):
            info.append(f"protocol `{_repo_relative(meta['protocol_file'])}`")
        if meta.get("density") is not None:
            info.append(f"obstacle density {meta['density']}")
        if meta.get("seed") is not None:
            info.append(f"generator seed {meta['seed']}")
        if meta.get("wall_time_s") is not None:
            info.append(f"wall time {meta['wall_time_s']:.0f} s with {meta.get('workers', '?')} worker(s)")
        if meta.get("versions"):
            info.append("versions " + ", ".join(f"{k} {v}" for k, v in meta["versions"].items()))
        if info:
            lines += ["Evaluation: " + "; ".join(info) + ".", ""]
    if len(runs) > 1:
        lines += ["A row measured in several of these files is taken from the first one listed.", ""]
    lines += evaluation_section(evaluation, policy, metadata, eval_path)
    return lines


def append_evaluation(checkpoint: str | Path, eval_path, out: str | Path, title: str,
                      command: str) -> str:
    """Append an evaluation section (tables and re-run commands) to the existing card `out` of
    `checkpoint`, e.g. its protocol under the coordination layer, for a card whose training run
    directory is gone (a new card would lose its compute and curves). The card must name the
    checkpoint's SHA-256; returns the appended text."""
    from mapf_fleet.models.checkpoint import CheckpointError, load_checkpoint

    checkpoint, out = Path(checkpoint), Path(out)
    try:
        _, metadata = load_checkpoint(checkpoint)
    except CheckpointError as exc:
        raise CardError(f"--checkpoint: {exc}") from exc
    if not out.is_file():
        raise CardError(f"--append: {out}: no such card to append to")
    card = out.read_text()
    if _sha256(checkpoint) not in card:
        raise CardError(f"--append: {out} does not name the SHA-256 of {checkpoint}: the card of "
                        f"another checkpoint (or an older version of it)")
    evaluation, eval_path = load_evaluations(eval_path)
    policy = match_policy(evaluation, checkpoint, eval_path)
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    lines = evaluation_block(evaluation, policy, metadata, eval_path, title)
    lines.insert(2, f"Appended {now} by `{command}`.")
    lines.insert(3, "")
    return "\n" + "\n".join(lines) + "\n"


def build_card(checkpoint: str | Path, eval_path: str | Path, *, run_dir: str | Path | None = None,
               out: str | Path | None = None, curves: str | Path | None = None,
               command: str | None = None, compare: list[str | Path] | None = None) -> str:
    """The card's Markdown (and the curves PNG when `curves` is given); `compare`: other
    checkpoints of the same evaluation JSON to show side by side."""
    from mapf_fleet.models.checkpoint import CheckpointError, code_version, load_checkpoint

    checkpoint = Path(checkpoint)
    try:
        model, metadata = load_checkpoint(checkpoint)
    except CheckpointError as exc:
        raise CardError(f"--checkpoint: {exc}") from exc
    evaluation, eval_path = load_evaluations(eval_path)
    policy = match_policy(evaluation, checkpoint, eval_path)
    run = read_run_dir(run_dir, checkpoint, metadata) if run_dir is not None else None
    if curves is not None and (run is None or run.tb_dir is None):
        raise CardError(f"--curves {curves}: needs --run-dir with a tb/ folder of TensorBoard scalars"
                        + ("" if run is None else f" ({run.path}/tb is missing)"))
    card_dir = Path(out).parent if out is not None else Path.cwd()
    curriculum = metadata.get("curriculum") or {}
    summary = model_summary(model, metadata)
    steps = int(metadata["learner_steps"])
    # the update the run reached, when it trained on after this checkpoint (else None)
    run_updates = (run.result or {}).get("learner_updates") if run else None
    later_updates = run_updates if isinstance(run_updates, int) and run_updates > steps else None
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")

    lines = [f"# Model card: {checkpoint.stem}", ""]
    lines.append(f"Generated {now} by `{command or 'mapf-fleet card'}`. Every figure below is read from "
                 f"`{checkpoint.name}`'s metadata, the evaluation JSON(s) `{eval_path.name}`"
                 + (", the training run directory" if run else "") + " or the paper's tables.")
    lines += ["", "## What it is", "", "| | |", "|---|---|"]
    setting = curriculum.get("setting")
    if isinstance(setting, (list, tuple)) and len(setting) == 2:
        setting_text = f"{setting[0]} agent{'s' if setting[0] != 1 else ''} on {setting[1]}x{setting[1]}"
    else:
        setting_text = "not recorded" if setting is None else str(setting)
    alpha_star = curriculum.get("alpha_star")
    if alpha_star is None and run and run.result:
        alpha_star = run.result.get("alpha_star")
    passed = curriculum.get("alpha_passed")
    facts = [
        ("algorithm", metadata["algorithm"].upper()),
        ("network", f"preset `{summary['preset']}`, {summary['parameters']:,} parameters"),
        ("alpha (cooperation coefficient of this checkpoint)", f"{float(metadata['alpha']):g}"),
        ("curriculum stage", str(curriculum.get("stage", "not recorded"))),
        ("curriculum setting reached (stage 1)", setting_text),
        ("alphas that passed the gate (stage 2)", "none" if not passed else ", ".join(f"{a:g}" for a in passed)),
        ("alpha* (stage 2)", _alpha_star_text(alpha_star, metadata.get("training_config") or {})),
        ("learner steps", f"{metadata['learner_steps']:,}"),
        ("observation padding / action order", f"{metadata['obs_padding']} / {', '.join(metadata['action_order'])}"),
        ("checkpoint written", str(metadata.get("created", "not recorded"))),
        ("code version of the checkpoint", _version_text(metadata.get("code_version"))),
        ("code that trained it (per training session)", _trained_with_text(metadata)),
        ("checkpoint SHA-256", f"`{_sha256(checkpoint)}`"),
    ]
    if curriculum.get("note"):
        facts.insert(3, ("note", str(curriculum["note"])))
    if run is not None:
        if run.checkpoint_in_run:
            facts.append(("in the run directory as", f"`checkpoints/{run.checkpoint_in_run}` (same bytes)"))
        if run.result:
            stop = str(run.result.get("stop_reason") or "–")
            if later_updates is not None:
                stop += f" (at update {later_updates:,}, after this checkpoint)"
            facts.append(("run stop reason", stop))
    lines += [f"| {k} | {v} |" for k, v in facts]

    lines += ["", "## Training configuration", ""]
    training_config = dict(metadata.get("training_config") or {})
    diff, closest, closest_note = training_config_diff(training_config)
    if closest:
        lines.append(f"Closest shipped config file: `{closest}` ({closest_note}). Train again with "
                     f"`mapf-fleet train --config {closest} ...`.")
    if diff:
        lines += ["", f"Fields that differ from the paper's recipe for {metadata['algorithm'].upper()} "
                  "(`preset: " + metadata["algorithm"] + "` in `mapf_fleet.training.config`):", "",
                  "| field | this run | paper |", "|---|---|---|"]
        lines += [f"| `{k}` | `{v!r}` | `{p!r}` |" for k, v, p in diff]
    elif not closest:
        lines.append("The checkpoint's training_config is not a full trainer configuration; as recorded:")
    lines += ["", "<details><summary>full training configuration (checkpoint metadata)</summary>", "",
              _yaml_block(training_config), "", "</details>"]

    lines += ["", "## Compute", ""]
    compute = compute_spent(run, metadata)
    if compute is None:
        lines.append("Not recorded: no run directory given and the checkpoint holds no elapsed time.")
    elif compute.cpu_hours is None:
        lines.append(f"Wall time {compute.wall_seconds / 3600:.2f} h ({compute.source}); CPU-hours unknown: "
                     f"{compute.how}.")
    else:
        lines.append(f"**{compute.cpu_hours:.2f} CPU-hours** = wall time {compute.wall_seconds / 3600:.2f} h "
                     f"({compute.source}, summed over resumed sessions) x {compute.cpus} CPU(s) "
                     f"({compute.how}). CPUs reserved, not measured utilisation; "
                     + ("up to this checkpoint." if compute.source.startswith(CHECKPOINT_POINT)
                        else "the whole run, of which this checkpoint may be an intermediate point."))
    if compute is not None and not compute.source.startswith(CHECKPOINT_POINT) and later_updates is not None:
        lines.append(f"This checkpoint is an intermediate point (update {steps:,}) of a "
                     f"run that went on to update {later_updates:,}: the figures here are the whole run's, "
                     "an upper bound of the compute up to this checkpoint, which it does not record.")
    if compute is not None and compute.measured_cpu_seconds is not None:
        measured = (f"Measured: **{compute.measured_cpu_seconds / 3600:.2f} CPU-hours** of process CPU "
                    "time (the trainer's process and its actor processes, `counters.cpu_seconds`; "
                    "Ray's daemons not included)")
        if compute.measured_from_elapsed > 0:
            measured += (f", over the last {(compute.wall_seconds - compute.measured_from_elapsed) / 3600:.2f} h "
                         f"of the run's wall time only: the first {compute.measured_from_elapsed / 3600:.2f} h "
                         "ran before the trainer measured CPU time")
        lines.append(measured + ".")
    counters = (run.result or {}).get("counters") if run else None
    if isinstance(counters, dict):
        parts = [f"{counters[k]:,} {k.replace('_', ' ')}" for k in ("episodes", "env_steps", "agent_steps")
                 if isinstance(counters.get(k), int)]
        if parts:
            lines.append(f"Run totals (result.json): {', '.join(parts)}.")
    for note in (run.notes if run else []):
        lines.append(f"Note: {note}.")

    lines += ["", "## Training curves", ""]
    if curves is not None:
        scalars, cut = scalars_up_to(read_scalars(run.tb_dir), steps)
        plotted = plot_curves(scalars, Path(curves), f"{checkpoint.stem}: {metadata['algorithm'].upper()}")
        lines.append(f"![training curves]({_relative(Path(curves), card_dir)})")
        lines.append("")
        upto = (f"; up to this checkpoint's update {steps:,}, the run logged on to "
                f"update {cut:,}" if cut is not None else "")
        lines.append(f"From the TensorBoard scalars of the run directory (x axis: learner updates{upto}). "
                     "Last values:")
        lines += ["", "| scalar | last value | at update |", "|---|---:|---:|"]
        for tag in CURVE_TAGS:
            if scalars.get(tag):
                step, value = scalars[tag][-1]
                lines.append(f"| `{tag}` | {value:.4g} | {step:,} |")
        missing = [t for t in CURVE_TAGS if t not in plotted]
        if missing:
            lines.append(f"\nNot logged in this run: {', '.join(f'`{t}`' for t in missing)}.")
    else:
        lines.append("No curves: the card was written without `--run-dir` and `--curves`.")

    lines += [""] + evaluation_block(evaluation, policy, metadata, eval_path,
                                     "Evaluation (the paper's protocol)")
    if compare:
        others = []
        for item in map(str, compare):
            path_text, _, run_text = item.partition("=")
            path, other_run_dir = Path(path_text), (Path(run_text) if run_text else None)
            try:
                meta = load_checkpoint(path)[1]
            except (CheckpointError, FileNotFoundError) as exc:
                raise CardError(f"--compare {path}: {exc}") from exc
            other_run = read_run_dir(other_run_dir, path, meta) if other_run_dir else None
            others.append((path, meta, other_run))
        lines += comparison_section(evaluation, policy, metadata, eval_path, others, run)
    lines += ["## Versions", "",
              f"- card written {now} with code {_version_text(code_version())}",
              f"- checkpoint written {metadata.get('created', '?')} with code {_version_text(metadata.get('code_version'))}",
              ""]
    return "\n".join(lines)


def _trained_with_text(metadata: dict) -> str:
    sessions = (metadata.get("extra") or {}).get("trained_with_code")
    if not isinstance(sessions, list) or not sessions:
        return "not recorded (runs begun before the trainer recorded it)"

    def one(v: dict) -> str:
        text = f"{_version_text(v)} from update {v.get('from_update', '?')}"
        if v.get("overrides"):
            changed = ", ".join(f"`{k}={value!r}`" for k, value in v["overrides"].items())
            text += f" (resumed with {changed})"
        return text

    return "; ".join(one(v) for v in sessions if isinstance(v, dict))


def _alpha_star_text(alpha_star, training_config: dict) -> str:
    """alpha* as the card states it. A fixed-alpha run with the gate off (success_threshold >= 1:
    no window can exceed it) has no alpha* by design: it trained one alpha for a budget of
    learner updates, which is how an A/B at matched compute is run."""
    if alpha_star is not None:
        return f"{float(alpha_star):g}"
    if (training_config.get("alpha_mode") == "fixed"
            and float(training_config.get("success_threshold", 0.9)) >= 1.0):
        return (f"none by design: fixed alpha {float(training_config.get('fixed_alpha', 0)):g} with the "
                "gate off (`success_threshold: 1.0`), trained for a budget of learner updates")
    return "stage 2 did not finish"


def _version_text(version: Any) -> str:
    if not isinstance(version, dict):
        return "not recorded"
    commit = version.get("git_commit")
    return f"mapf_fleet {version.get('package', '?')}" + (f", git {commit[:12]}" if commit else ", git commit unknown")


def _repo_relative(path: str) -> str:
    try:
        return Path(path).resolve().relative_to(REPO_ROOT).as_posix()
    except ValueError:
        return path


# ---- command ------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mapf-fleet card", description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", required=True, help="the checkpoint file (models/X.pt)")
    p.add_argument("--eval", required=True, nargs="+", metavar="JSON",
                   help="JSON(s) of `mapf-fleet evaluate --json` on it (several are read as one)")
    p.add_argument("--run-dir", help="the trainer's run directory (config, counters, tb/ scalars)")
    p.add_argument("--out", required=True, help="Markdown file to write (models/X.md)")
    p.add_argument("--curves", metavar="PNG", help="write the training curves here (needs --run-dir)")
    p.add_argument("--append", metavar="TITLE",
                   help="append the --eval section under this heading to the existing card --out "
                        "(which must name the checkpoint's SHA-256) instead of writing a new card")
    p.add_argument("--compare", nargs="+", metavar="CHECKPOINT", default=[],
                   help="other checkpoints evaluated in the --eval JSON(s), as CHECKPOINT or "
                        "CHECKPOINT=RUN_DIR (its run directory, for what the checkpoint does not "
                        "record): a side-by-side table of how each was trained, the compute up to it "
                        "and its success rates")
    return p


def main(argv: list[str] | None = None) -> int:
    import shlex

    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if args.append:
        try:
            text = append_evaluation(args.checkpoint, args.eval, args.out, args.append,
                                     "mapf-fleet card " + shlex.join(argv))
        except CardError as exc:
            print(f"mapf-fleet card: {exc}", file=sys.stderr)
            return 2
        with open(args.out, "a") as handle:
            handle.write(text)
        print(f"appended to {args.out}")
        return 0
    try:
        text = build_card(args.checkpoint, args.eval, run_dir=args.run_dir, out=args.out,
                          curves=args.curves, command="mapf-fleet card " + shlex.join(argv),
                          compare=args.compare)
    except (CardError, FileNotFoundError) as exc:
        print(f"mapf-fleet card: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(f"wrote {out}" + (f" and {args.curves}" if args.curves else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
