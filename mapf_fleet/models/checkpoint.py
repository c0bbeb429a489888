"""Checkpoint files: one file per checkpoint, weights plus the metadata needed to use them.

File layout (a torch.save'd dict of tensors and plain data, loadable with weights_only=True):
    {"format": "mapf_fleet.checkpoint", "format_version": 1,
     "state_dict": {name: tensor}, "metadata": {...}}
metadata fields:
    algorithm        "dhc" | "dcc"
    model_config     ModelConfig.to_dict() (its `observation`: "paper" or "cost_to_go"; files
                     written before the field existed have none and load as "paper")
    obs_radius       int (= model_config["obs_radius"])
    obs_padding      "obstacle" (off-map cells are obstacles in channel 1)
    action_order     ["stay", "up", "down", "left", "right"]
    alpha            cooperation coefficient of the reward, float in [0, 1]
    curriculum       {"stage": ..., "setting": ...} plain data (scale and alpha curriculum state)
    learner_steps    int >= 0
    training_config  dict (the TrainConfig as plain data)
    code_version     {"package": "0.1.0", "git_commit": "..." or None}
    evaluation       dict or None (evaluation summary)
    created          ISO 8601 UTC time of writing
    extra            dict, free plain data (optional)
    rankings         {conflict rule: ranking} (optional): the ranking the weights were
                     trained behind each rule (the trainer and DAgger write {conflict_rule:
                     ranking} of their config, older files {shield: preferences}); the
                     evaluator and the policy nodes default to it under that rule
                     (coordination.ranking.default_ranking)
    guidance         str (optional): the guidance graph the heuristic channels were trained to
                     read (a `grid.guidance_made.GuidanceSource` spelling: none, highways, a
                     file; the trainer and DAgger write their config's); the evaluator and
                     `mapf-fleet up` run the checkpoint under it unless --guidance is given.
                     Absent (files written before the field existed, e.g. models/default.pt):
                     the fleet's guidance (coordination.rules.FLEET_GUIDANCE)
Writes are atomic (temporary file in the same directory + os.replace), so a reader never sees
half a file.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import nn

from mapf_fleet.files import atomic_write
from mapf_fleet.version import code_version  # noqa: F401 - re-exported
from mapf_fleet.grid.actions import ACTION_NAMES

from .config import ALGORITHMS, ModelConfig

FORMAT = "mapf_fleet.checkpoint"
FORMAT_VERSION = 1
OBS_PADDING = "obstacle"
ACTION_ORDER = list(ACTION_NAMES)
# Fields the caller supplies (the rest are derived from the model and the code).
REQUIRED_FIELDS = ("alpha", "curriculum", "learner_steps", "training_config")
OPTIONAL_FIELDS = ("evaluation", "extra", "rankings", "guidance")


class CheckpointError(ValueError):
    """A checkpoint file is missing, unreadable or incompatible; the message names the field."""


def build_model(config: ModelConfig) -> nn.Module:
    """A fresh DHCNetwork or DCCNetwork for `config`."""
    from .dcc import DCCNetwork
    from .dhc import DHCNetwork

    return DHCNetwork(config) if config.algo == "dhc" else DCCNetwork(config)


def with_observation(model: nn.Module, observation: str) -> nn.Module:
    """`model` rebuilt to read `observation` (e.g. a "paper" network warm-started as a
    "cost_to_go" one): every weight is copied and the first conv's weights of the channels
    `observation` adds are zero, so the new network's outputs equal `model`'s on the same
    observations, whatever the added channel holds, until training moves them. `model` itself
    when it already reads `observation`; a network cannot drop channels it was trained on."""
    config = model.config
    if observation == config.observation:
        return model
    wider = dataclasses.replace(config, observation=observation)
    have, need = config.obs_shape[0], wider.obs_shape[0]
    if need < have:
        raise ValueError(f"with_observation: a {config.observation!r} network reads {have} "
                         f"channels, {observation!r} only {need}: it cannot drop channels")
    widened = build_model(wider)
    own, state = model.state_dict(), {}
    for name, target in widened.state_dict().items():
        weight = own[name]
        if weight.shape != target.shape:  # the first conv: (out, have, k, k) -> (out, need, k, k)
            grown = torch.zeros_like(target)
            grown[:, :have] = weight
            weight = grown
        state[name] = weight
    widened.load_state_dict(state)
    return widened.to(next(model.parameters()).device).train(model.training)


def save_checkpoint(path, model: nn.Module, metadata: Mapping[str, Any]) -> Path:
    """Write `model`'s weights and `metadata` (REQUIRED_FIELDS, optional OPTIONAL_FIELDS)."""
    path = Path(path)
    config = getattr(model, "config", None)
    if not isinstance(config, ModelConfig):
        raise TypeError(f"save_checkpoint: model has no ModelConfig `config` "
                        f"({type(model).__name__})")
    unknown = sorted(set(metadata) - set(REQUIRED_FIELDS) - set(OPTIONAL_FIELDS))
    if unknown:
        raise ValueError(f"save_checkpoint {path}: unknown metadata field(s) {unknown}; "
                         f"allowed {list(REQUIRED_FIELDS + OPTIONAL_FIELDS)}")
    missing = [name for name in REQUIRED_FIELDS if name not in metadata]
    if missing:
        raise ValueError(f"save_checkpoint {path}: missing metadata field(s) {missing}")
    full = {
        "algorithm": config.algo,
        "model_config": config.to_dict(),
        "obs_radius": config.obs_radius,
        "obs_padding": OBS_PADDING,
        "action_order": list(ACTION_ORDER),
        "alpha": metadata["alpha"],
        "curriculum": metadata["curriculum"],
        "learner_steps": metadata["learner_steps"],
        "training_config": metadata["training_config"],
        "code_version": code_version(),
        "evaluation": metadata.get("evaluation"),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "extra": metadata.get("extra", {}),
    }
    for name in ("rankings", "guidance"):  # absent, not empty, when not given: files as before
        if name in metadata:
            full[name] = metadata[name]
    _check_metadata(full, str(path))
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "state_dict": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
        "metadata": full,
    }
    atomic_write(path, lambda handle: torch.save(payload, handle))
    return path


def read_checkpoint(path, map_location="cpu") -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """(state_dict, metadata) of a checkpoint, with every metadata field checked."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt/truncated/unsafe files
        # one line: torch's own message runs to a page (every command prints this error as one)
        first = (str(exc).strip().splitlines() or [""])[0]
        raise CheckpointError(
            f"{path}: not a readable checkpoint (corrupt, truncated or not weights-only): "
            f"{type(exc).__name__}: {first}") from exc
    if not isinstance(payload, dict):
        raise CheckpointError(f"{path}: top level: expected a dict, found {type(payload).__name__}")
    _expect(path, "format", payload.get("format"), FORMAT)
    _expect(path, "format_version", payload.get("format_version"), FORMAT_VERSION)
    state_dict, metadata = payload.get("state_dict"), payload.get("metadata")
    if not isinstance(state_dict, dict):
        raise CheckpointError(f"{path}: field state_dict: expected a dict of tensors, "
                              f"found {type(state_dict).__name__}")
    if not isinstance(metadata, dict):
        raise CheckpointError(f"{path}: field metadata: expected a dict, "
                              f"found {type(metadata).__name__}")
    _check_metadata(metadata, str(path))
    return state_dict, metadata


def load_checkpoint(path, map_location="cpu") -> tuple[nn.Module, dict[str, Any]]:
    """(model in eval mode, metadata). Raises CheckpointError naming the bad field."""
    state_dict, metadata = read_checkpoint(path, map_location)
    config = ModelConfig.from_dict(metadata["model_config"])
    model = build_model(config)
    expected = model.state_dict()
    for name, tensor in expected.items():
        if name not in state_dict:
            raise CheckpointError(f"{path}: state_dict: missing weight {name!r} "
                                  f"(expected shape {tuple(tensor.shape)})")
        found = state_dict[name]
        if not isinstance(found, torch.Tensor) or found.shape != tensor.shape:
            shape = tuple(found.shape) if isinstance(found, torch.Tensor) else type(found).__name__
            raise CheckpointError(f"{path}: state_dict[{name!r}]: expected shape "
                                  f"{tuple(tensor.shape)}, found {shape}")
    unexpected = sorted(set(state_dict) - set(expected))
    if unexpected:
        raise CheckpointError(f"{path}: state_dict: unexpected weight(s) {unexpected[:5]}")
    model.load_state_dict(state_dict)
    model.to(map_location if map_location is not None else "cpu")
    return model.eval(), metadata


# ---- validation -------------------------------------------------------------------------


def _expect(path, field: str, found: Any, expected: Any) -> None:
    if found != expected:
        raise CheckpointError(f"{path}: field {field}: expected {expected!r}, found {found!r}")


def _check_metadata(meta: Mapping[str, Any], path: str) -> None:
    def fail(field: str, expected: str, found: Any) -> None:
        raise CheckpointError(
            f"{path}: field metadata.{field}: expected {expected}, found {found!r}")

    for name in ("algorithm", "model_config", "obs_radius", "obs_padding", "action_order",
                 *REQUIRED_FIELDS, "code_version", "evaluation"):
        if name not in meta:
            raise CheckpointError(f"{path}: field metadata.{name}: missing")
    if meta["algorithm"] not in ALGORITHMS:
        fail("algorithm", f"one of {ALGORITHMS}", meta["algorithm"])
    if not isinstance(meta["model_config"], Mapping):
        fail("model_config", "a dict", meta["model_config"])
    try:
        config = ModelConfig.from_dict(meta["model_config"])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: field metadata.model_config: {exc}") from exc
    if config.algo != meta["algorithm"]:
        fail("model_config.algo", f"{meta['algorithm']!r} (= metadata.algorithm)", config.algo)
    if meta["obs_radius"] != config.obs_radius:
        fail("obs_radius", f"{config.obs_radius} (= model_config.obs_radius)", meta["obs_radius"])
    if meta["obs_padding"] != OBS_PADDING:
        fail("obs_padding", repr(OBS_PADDING), meta["obs_padding"])
    if list(meta["action_order"]) != ACTION_ORDER:
        fail("action_order", repr(ACTION_ORDER), meta["action_order"])
    alpha = meta["alpha"]
    if isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not 0.0 <= alpha <= 1.0:
        fail("alpha", "a number in [0, 1]", alpha)
    steps = meta["learner_steps"]
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
        fail("learner_steps", "an int >= 0", steps)
    for name in ("curriculum", "training_config", "code_version"):
        if not isinstance(meta[name], Mapping):
            fail(name, "a dict", meta[name])
    if meta["evaluation"] is not None and not isinstance(meta["evaluation"], Mapping):
        fail("evaluation", "a dict or None", meta["evaluation"])
    if not isinstance(meta.get("extra", {}), Mapping):
        fail("extra", "a dict", meta.get("extra"))
    if "rankings" in meta:
        _check_rankings(meta["rankings"], fail)
    if "guidance" in meta and not isinstance(meta["guidance"], str):
        fail("guidance", "a guidance spelling (none, highways, a file)", meta["guidance"])
    for name in meta:
        _check_plain(meta[name], f"metadata.{name}", path)


def _check_rankings(rankings: Any, fail) -> None:
    """metadata.rankings: {rule: ranking}, a coordinating rule (`coordination.rules.Rule`) and a
    ranking of coordination.ranking.Q_RANKINGS (a learned policy ranks by its Q-values)."""
    from mapf_fleet.coordination.ranking import Q_RANKINGS
    from mapf_fleet.coordination.rules import COORDINATED_RULES, Rule

    if not isinstance(rankings, Mapping):
        fail("rankings", "a dict {conflict rule: ranking}", rankings)
    for rule, mode in rankings.items():
        try:
            coordinated = Rule.parse(rule).coordinated
        except ValueError:
            coordinated = False
        if not coordinated:
            fail("rankings", f"conflict rules among {COORDINATED_RULES}", rule)
        if mode not in Q_RANKINGS:
            fail(f"rankings.{rule}", f"one of {Q_RANKINGS}", mode)


def _check_plain(value: Any, where: str, path: str) -> None:
    """Only plain data survives torch.load(weights_only=True) without surprises."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return
    if isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            _check_plain(item, f"{where}[{index}]", path)
        return
    if isinstance(value, Mapping):
        for key, item in value.items():
            if not isinstance(key, str):
                raise CheckpointError(f"{path}: field {where}: keys must be str, found {key!r}")
            _check_plain(item, f"{where}.{key}", path)
        return
    raise CheckpointError(f"{path}: field {where}: expected plain data (dict/list/str/number/"
                          f"bool/None), found {type(value).__name__}")
