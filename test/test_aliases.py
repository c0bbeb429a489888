"""The deprecated spellings of the conflict rule (`shield`, `--shield`, `none`) and of the
ranking (`preferences`, `shield_preferences`, `--preferences`) still work for one release with
one warning line naming the old and the new spelling, and every shipped checkpoint (written
before the rename, its training_config under the old keys) still loads and reads."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapf_fleet.aliases import renamed_keys, renamed_options

MODELS = Path(__file__).resolve().parents[1] / "models"
SHIPPED = sorted(MODELS.glob("*.pt")) + sorted((MODELS / "archive").glob("*.pt"))


def _warnings(capsys) -> list[str]:
    return [line for line in capsys.readouterr().err.splitlines() if "deprecated" in line]


def test_old_options_are_rewritten_with_one_warning_each(capsys):
    argv = ["--checkpoint", "heuristic", "--shield", "none", "pibt_anchor", "--preferences", "q",
            "--sizes", "40"]
    assert renamed_options(argv, "mapf-fleet evaluate") == [
        "--checkpoint", "heuristic", "--conflict-rule", "revert", "pibt_anchor", "--ranking", "q",
        "--sizes", "40"]
    assert _warnings(capsys) == [
        "mapf-fleet evaluate: --shield is deprecated, use --conflict-rule",
        "mapf-fleet evaluate: --conflict-rule: 'none' is deprecated, use 'revert'",
        "mapf-fleet evaluate: --preferences is deprecated, use --ranking"]
    assert renamed_options(["--shield=pibt", "--preferences=q"], "x") == [
        "--conflict-rule=pibt", "--ranking=q"]
    # new spellings pass unchanged and silently; "none" elsewhere is not a rule
    new = ["--conflict-rule", "revert", "pibt", "--ranking", "q", "--testsets", "none"]
    capsys.readouterr()
    assert renamed_options(new, "x") == new and _warnings(capsys) == []


def test_evaluate_and_lifelong_parse_the_old_options_as_the_new():
    from mapf_fleet.evaluation.cli import build_parser
    from mapf_fleet.evaluation.lifelong import build_parser as lifelong_parser

    old = build_parser().parse_args(renamed_options(
        ["--shield", "none", "pibt", "--preferences", "q_then_distance"], "x"))
    new = build_parser().parse_args(["--conflict-rule", "revert", "pibt",
                                     "--ranking", "q_then_distance"])
    assert (old.conflict_rule, old.ranking) == (new.conflict_rule, new.ranking)
    args = lifelong_parser().parse_args(renamed_options(
        ["--lifelong", "--shield", "pibt_anchor", "--preferences", "q"], "x"))
    assert (args.conflict_rule, args.ranking) == (["pibt_anchor"], "q")


def test_evaluate_main_accepts_the_old_options(tmp_path, capsys):
    from mapf_fleet.evaluation.cli import main

    common = ["--checkpoint", "heuristic", "--no-references", "--kinds", "dense", "--agents",
              "8", "--instances", "2", "--cache-dir", str(tmp_path), "--quiet"]
    assert main([*common, "--shield", "pibt_anchor", "--json", str(tmp_path / "old.json")]) == 0
    assert _warnings(capsys) == [
        "mapf-fleet evaluate: --shield is deprecated, use --conflict-rule"]
    assert main([*common, "--conflict-rule", "pibt_anchor", "--json", str(tmp_path / "new.json")]) == 0
    import json

    old, new = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("old", "new"))
    assert [r["episodes"] for r in old["results"]] == [r["episodes"] for r in new["results"]]
    assert old["metadata"]["policies"][0]["conflict_rule"] == "pibt_anchor"


def test_trainer_config_reads_the_old_keys(tmp_path, capsys):
    from mapf_fleet.training.config import TrainConfigError, config_from_dict, load_config

    old = config_from_dict({"shield": "pibt_anchor", "shield_preferences": "q_then_distance",
                            "shield_replay": "preferred"})
    assert (old.conflict_rule, old.ranking, old.replay_action) == ("pibt_anchor",
                                                                   "q_then_distance", "preferred")
    assert _warnings(capsys) == ["<dict>: key 'shield' is deprecated, use 'conflict_rule'",
                                 "<dict>: key 'shield_preferences' is deprecated, use 'ranking'",
                                 "<dict>: key 'shield_replay' is deprecated, use 'replay_action'"]
    path = tmp_path / "old.yaml"
    path.write_text("preset: dcc\nshield: none\n")
    assert load_config(path).conflict_rule == "revert"
    assert len(_warnings(capsys)) == 2  # the key and the value, each named once
    with pytest.raises(TrainConfigError, match="'shield' and 'conflict_rule' are the same key"):
        config_from_dict({"shield": "pibt", "conflict_rule": "pibt"})


def test_dagger_config_reads_the_old_keys(capsys):
    from mapf_fleet.training.dagger import config_from_dict

    cfg = config_from_dict({"shield": "pibt", "preferences": "q"})
    assert (cfg.conflict_rule, cfg.ranking) == ("pibt", "q")
    assert _warnings(capsys) == ["<dict>: key 'shield' is deprecated, use 'conflict_rule'",
                                 "<dict>: key 'preferences' is deprecated, use 'ranking'"]


def test_renamed_keys_quiet_reads_old_checkpoints_silently(capsys):
    assert renamed_keys({"shield": "none", "shield_preferences": "q"}, "x", quiet=True) == {
        "conflict_rule": "revert", "ranking": "q"}
    assert _warnings(capsys) == []


def test_the_ros_parameter_alias_is_the_shared_table():
    pytest.importorskip("yaml")
    from mapf_fleet.aliases import PARAMETERS
    from mapf_fleet.fleet.parameters import ALIASES, POLICY

    assert ALIASES is PARAMETERS
    assert all(new in POLICY for new in PARAMETERS.values())


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.relative_to(MODELS).as_posix())
def test_checkpoints_written_before_the_rename_load_and_read(path, capsys):
    """Every shipped checkpoint was written before the rename: it loads, its policy resolves a
    ranking under each coordinated rule, and its recorded training config reads with the old
    keys as fallback, silently."""
    from mapf_fleet.evaluation.model_card.facts import (dagger_record, dagger_training_text,
                                                        training_config_diff)
    from mapf_fleet.evaluation.policies import parse_policy, with_conflict_rule
    from mapf_fleet.models.checkpoint import load_checkpoint
    from mapf_fleet.training.config import config_from_dict

    model, meta = load_checkpoint(path)
    assert model is not None
    spec = parse_policy(str(path))
    assert with_conflict_rule(spec, "pibt_anchor").resolved_ranking
    recorded = meta.get("training_config") or {}
    if "shield" in recorded:  # an Ape-X run behind a rule, recorded under the old keys
        cfg = config_from_dict(recorded, source=str(path), quiet=True)
        assert cfg.conflict_rule == {"none": "revert"}.get(recorded["shield"], recorded["shield"])
        assert cfg.ranking == recorded["shield_preferences"]
        assert cfg.replay_action == recorded.get("shield_replay", "executed")
        diff, _, _ = training_config_diff(recorded)
        assert "conflict_rule" in dict((k, v) for k, v, _ in diff) or cfg.conflict_rule == "revert"
    record = dagger_record(meta)
    if record is not None:  # DAgger: {shield, preferences} of its config, now read as new
        text = dagger_training_text(record)
        assert f"behind `{meta['rankings'] and next(iter(meta['rankings']))}`" in text
        assert "`?`" not in text
    assert _warnings(capsys) == []
