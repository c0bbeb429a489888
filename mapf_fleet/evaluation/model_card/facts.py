"""What a checkpoint is, as the card's first sections state it: its network (`model_summary`),
how its training config differs from the paper's recipe and which shipped config file is closest
(`training_config_diff`), alpha*, and the code versions recorded in its metadata."""

from __future__ import annotations

from typing import Any

from mapf_fleet import paths
from mapf_fleet.aliases import renamed_keys


def model_summary(model, metadata: dict) -> dict:
    """Preset name (or "custom"; the sizes: a preset's network may read another observation),
    parameter count and observation ("paper" or "cost_to_go")."""
    from mapf_fleet.models.config import PRESETS, ModelConfig

    config = ModelConfig.from_dict(metadata["model_config"])
    preset = "custom"
    for name in PRESETS:
        if ModelConfig.preset(metadata["algorithm"], name, observation=config.observation) == config:
            preset = name
    return {"preset": preset, "parameters": sum(p.numel() for p in model.parameters()),
            "observation": config.observation}


def training_config_diff(training_config: dict) -> tuple[list[tuple[str, Any, Any]], str | None, str | None]:
    """(fields that differ from the paper's recipe for the algorithm as (name, value, paper value),
    the closest config file of config/training/ or its experiments/ and how it differs; on a tie
    the one a user trains with), or ([], None, None) when the
    training config is not a TrainConfig."""
    try:
        from mapf_fleet.training.config import TrainConfigError, config_from_dict, load_config
    except ImportError:
        return [], None, None
    try:
        config = config_from_dict(dict(training_config), source="checkpoint training_config",
                                  quiet=True).to_dict()
        paper = config_from_dict({"preset": config["algo"]}, source="paper preset").to_dict()
    except (TrainConfigError, KeyError, TypeError):
        return [], None, None
    diff = [(k, v, paper.get(k)) for k, v in config.items() if paper.get(k) != v]
    best, best_diff = None, None
    shipped_dir = paths.data_path("config", "training")
    for path in [*sorted(shipped_dir.glob("*.yaml")),
                 *sorted(shipped_dir.glob("experiments/*.yaml"))]:
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
    return diff, f"config/training/{best.relative_to(shipped_dir).as_posix()}", note


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


def dagger_record(metadata: dict) -> dict | None:
    """The DAgger round's record (`extra.dagger`, written by `mapf-fleet dagger`) with its
    configuration (`training_config.dagger`) under "config", or None for other checkpoints."""
    if (metadata.get("curriculum") or {}).get("stage") != "dagger":
        return None
    record = (metadata.get("extra") or {}).get("dagger")
    if not isinstance(record, dict):
        return None
    config = (metadata.get("training_config") or {}).get("dagger")
    return {**record, "config": config if isinstance(config, dict) else {}}


def dagger_training_text(record: dict) -> str:
    """One line: what a DAgger checkpoint trained on and how."""
    cfg = record["config"]
    rounds = cfg.get("rounds")
    of = f" of {rounds}" if isinstance(rounds, int) else ""
    cfg = renamed_keys(cfg, "checkpoint training_config.dagger", quiet=True)  # older checkpoints
    return (f"DAgger round {record.get('round', '?')}{of} behind `{cfg.get('conflict_rule', '?')}` "
            f"(ranking `{cfg.get('ranking', '?')}`), {cfg.get('loss', '?')} loss on LaCAM labels")


def dagger_facts(record: dict) -> list[tuple[str, str]]:
    """The card's "What it is" rows for a DAgger checkpoint, in place of the Ape-X curriculum's
    (stage-1 setting, alpha gate, alpha*), which a DAgger round does not have."""
    def count(key: str) -> str:
        value = record.get(key)
        return f"{value:,}" if isinstance(value, int) else "not recorded"

    cpu = record.get("cpu_seconds")
    init = record.get("init_checkpoint") or record["config"].get("init_checkpoint")
    return [
        ("training", dagger_training_text(record)),
        ("initialised from", "not recorded" if not init
         else f"`{init}` (the path as the run named it when it began)"),
        ("labels", f"{count('labels')} (every agent of {count('labelled_states')} labelled "
                   f"states, {count('episodes')} episodes)"),
        ("states LaCAM left unlabelled", f"{count('unsolved')} unsolved within the limit, "
                                         f"{count('too_long')} with a plan too long to trust"),
        ("updates in DAgger", count("updates")),
        ("DAgger compute to this checkpoint",
         "not recorded" if not isinstance(cpu, (int, float))
         else f"{cpu / 3600:.2f} CPU-hours measured (process CPU time of the driver and its "
              "workers, `extra.dagger.cpu_seconds`), beside the init checkpoint's own"),
    ]


def rankings_text(metadata: dict) -> str | None:
    """The rankings a checkpoint records (`{rule: mode}`), as one line; None when it records none."""
    rankings = metadata.get("rankings")
    if not isinstance(rankings, dict) or not rankings:
        return None
    return ", ".join(f"`{mode}` under `{rule}`" for rule, mode in rankings.items())
