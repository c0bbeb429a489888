"""Checkpoint files: round trip, atomic writes, and a clear error for each kind of bad file."""

from __future__ import annotations

import fractions

import pytest
import torch

from mapf_fleet.models import (
    CheckpointError, DCCNetwork, DHCNetwork, ModelConfig, load_checkpoint, save_checkpoint,
)
from mapf_fleet.models.checkpoint import FORMAT, FORMAT_VERSION

META = {
    "alpha": 0.2,
    "curriculum": {"stage": "alpha", "setting": {"map_size": 40, "num_agents": 12}},
    "learner_steps": 1234,
    "training_config": {"batch_size": 192, "lr": 1e-4, "gamma": 0.99},
    "evaluation": {"40x40/16": {"success_rate": 0.5}},
}


@pytest.fixture(params=["dhc", "dcc"])
def model(request):
    torch.manual_seed(0)
    config = ModelConfig.preset(request.param, "small")
    return DHCNetwork(config) if request.param == "dhc" else DCCNetwork(config)


def test_round_trip_keeps_weights_and_metadata(tmp_path, model):
    path = save_checkpoint(tmp_path / "ckpt.pt", model, META)
    loaded, meta = load_checkpoint(path)
    assert type(loaded) is type(model) and loaded.config == model.config
    for (name, a), (_, b) in zip(model.state_dict().items(), loaded.state_dict().items()):
        assert torch.equal(a, b), name
    assert meta["algorithm"] == model.config.algo
    assert meta["obs_radius"] == 4 and meta["obs_padding"] == "obstacle"
    assert meta["action_order"] == ["stay", "up", "down", "left", "right"]
    assert meta["alpha"] == 0.2 and meta["learner_steps"] == 1234
    assert meta["curriculum"] == META["curriculum"]
    assert meta["training_config"] == META["training_config"]
    assert meta["evaluation"] == META["evaluation"]
    assert meta["code_version"]["package"]
    assert not loaded.training
    # No temporary file is left next to the checkpoint.
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]


def test_rankings_round_trip_and_old_files_have_none(tmp_path, model):
    """metadata.rankings {shield rule: preference mode}: the ranking the weights were trained
    behind (DAgger writes it); a file written without it has none (the rule's default)."""
    rankings = {"pibt_anchor": "q_then_distance", "pibt": "q"}
    _, meta = load_checkpoint(save_checkpoint(tmp_path / "r.pt", model,
                                              {**META, "rankings": rankings}))
    assert meta["rankings"] == rankings
    _, meta = load_checkpoint(save_checkpoint(tmp_path / "old.pt", model, META))
    assert "rankings" not in meta


@pytest.mark.parametrize("rankings, message", [
    ({"pibt_anchor": "sideways"},
     r"ckpt.pt: field metadata.rankings.pibt_anchor: expected one of .*found 'sideways'"),
    ({"pibt_anchor": "distance"},  # a learned policy ranks by its Q-values
     r"ckpt.pt: field metadata.rankings.pibt_anchor: expected one of .*found 'distance'"),
    ({"revert": "q"}, r"ckpt.pt: field metadata.rankings: expected conflict rules .*found 'revert'"),
    (["pibt_anchor", "q"], r"ckpt.pt: field metadata.rankings: expected a dict"),
])
def test_bad_rankings_are_refused_naming_file_field_and_value(tmp_path, model, rankings,
                                                              message):
    path = save_checkpoint(tmp_path / "ckpt.pt", model, META)
    _rewrite(path, lambda p: p["metadata"].update(rankings=rankings))
    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(path)
    with pytest.raises(CheckpointError, match=message):  # and never written
        save_checkpoint(tmp_path / "ckpt.pt", model, {**META, "rankings": rankings})


def test_overwrite_is_atomic_replacement(tmp_path, model):
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, model, META)
    save_checkpoint(path, model, {**META, "learner_steps": 5})
    assert load_checkpoint(path)[1]["learner_steps"] == 5


def test_missing_file(tmp_path):
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_checkpoint(tmp_path / "nothing.pt")


def test_truncated_file_names_the_file(tmp_path, model):
    path = save_checkpoint(tmp_path / "ckpt.pt", model, META)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="ckpt.pt.*not a readable checkpoint"):
        load_checkpoint(path)


def test_garbage_file(tmp_path):
    path = tmp_path / "junk.pt"
    path.write_bytes(b"this is not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_checkpoint(path)


def test_arbitrary_pickles_are_refused(tmp_path):
    # Any class outside torch's weights-only allow-list stands for code a pickle could run.
    path = tmp_path / "evil.pt"
    torch.save({"format": FORMAT, "obj": fractions.Fraction(1, 3)}, path)
    with pytest.raises(CheckpointError, match="weights-only"):
        load_checkpoint(path)


def _rewrite(path, change):
    payload = torch.load(path, weights_only=True)
    change(payload)
    torch.save(payload, path)


@pytest.mark.parametrize("change, message", [
    (lambda p: p.update(format_version=99), "format_version: expected 1, found 99"),
    (lambda p: p.update(format="other"), "field format"),
    (lambda p: p["metadata"].update(obs_padding="free"),
     "obs_padding: expected 'obstacle', found 'free'"),
    (lambda p: p["metadata"].update(action_order=["up", "down", "left", "right", "stay"]),
     "action_order"),
    (lambda p: p["metadata"].update(algorithm="ppo"), "metadata.algorithm"),
    (lambda p: p["metadata"].update(alpha=1.5), "metadata.alpha"),
    (lambda p: p["metadata"].update(learner_steps=-1), "learner_steps"),
    (lambda p: p["metadata"].update(obs_radius=3),
     r"obs_radius: expected 4 \(= model_config.obs_radius\), found 3"),
    (lambda p: p["metadata"]["model_config"].update(hidden_dim=-5), "model_config.*hidden_dim"),
    (lambda p: p["metadata"].pop("curriculum"), "metadata.curriculum: missing"),
    (lambda p: p.update(metadata=[1, 2]), "field metadata: expected a dict"),
])
def test_incompatible_metadata_names_the_field(tmp_path, model, change, message):
    path = save_checkpoint(tmp_path / "ckpt.pt", model, META)
    _rewrite(path, change)
    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(path)


def test_weights_of_another_size_name_the_tensor(tmp_path, model):
    path = save_checkpoint(tmp_path / "ckpt.pt", model, META)

    def widen(payload):
        name = next(iter(payload["state_dict"]))
        payload["state_dict"][name] = torch.zeros(3, 3)

    _rewrite(path, widen)
    with pytest.raises(CheckpointError, match=r"state_dict\[.*expected shape .* found \(3, 3\)"):
        load_checkpoint(path)

    def drop(payload):
        payload["state_dict"].pop("head.adv.weight")

    save_checkpoint(path, model, META)
    _rewrite(path, drop)
    with pytest.raises(CheckpointError, match="missing weight 'head.adv.weight'"):
        load_checkpoint(path)


def test_bad_metadata_is_refused_on_save(tmp_path, model):
    with pytest.raises(ValueError, match="missing metadata"):
        save_checkpoint(tmp_path / "a.pt", model, {"alpha": 0.1})
    with pytest.raises(ValueError, match="unknown metadata"):
        save_checkpoint(tmp_path / "a.pt", model, {**META, "alhpa": 0.1})
    with pytest.raises(CheckpointError, match="training_config.optimizer"):
        save_checkpoint(tmp_path / "a.pt", model,
                        {**META, "training_config": {"optimizer": object()}})
    assert not list(tmp_path.iterdir())
