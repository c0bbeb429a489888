"""The card's inputs, read and checked: the evaluator's JSON(s) (`load_evaluations`), which of
their rows is the checkpoint's (`match_policy`), and the trainer's run directory
(`read_run_dir`). Inputs that do not belong together raise `CardError` naming the file."""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path


class CardError(ValueError):
    """A card input is missing, malformed or belongs to another checkpoint; names the file."""


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
    # the checkpoint's own row is its row under `revert`; its rows under the coordination layer
    # (`--conflict-rule pibt`, label "<name> +PIBT...") are shown beside it by evaluation_section.
    # JSONs written before the rename name the rule "shield" and `revert` "none".
    entries.sort(key=lambda p: p.get("conflict_rule", p.get("shield")) not in (None, "none", "revert"))
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
        if expected != ModelConfig.from_dict(metadata["model_config"]):
            raise CardError(f"{where}: model_preset {preset!r} builds another network than the "
                            "checkpoint's model_config: the run directory belongs to another checkpoint")
