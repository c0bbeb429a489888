"""The committed labeller (labels from one kept plan) and the expert ceiling
(`mapf-fleet dagger --expert-ceiling`): tiny maps, seconds in all."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from mapf_fleet.coordination.planners import positions_to_actions
from mapf_fleet.grid.heuristic import bfs_distances_many
from mapf_fleet.grid.instance import generate_instance
from mapf_fleet.training import dagger
from mapf_fleet.training.dagger import ceiling
from mapf_fleet.training.dagger.labeller import (CommittedLabeller, KeptPyMAPFLabeller,
                                                  StuckLabeller)


def _state(inst, positions, step):
    dist = bfs_distances_many(inst.grid, inst.goals)
    return dagger.LabelState(inst.grid, positions, inst.goals, dist, step, 64)


def test_committed_labels_follow_the_kept_plan_and_replan_only_off_it():
    inst = generate_instance(10, 6, 0.1, 5)
    labeller = CommittedLabeller(planning_budget=2.0)
    labels, status = labeller.label(_state(inst, inst.starts, 0))
    plan = labeller.expert.keeper.plan.copy()
    assert status == "ok" and labeller.replans == 1 and len(plan) >= 3
    assert labels.tolist() == positions_to_actions(plan[:2])[0].tolist()
    # the rollout followed the labels: the next labels are the same plan's next moves, no re-plan
    labels, status = labeller.label(_state(inst, plan[1], 1))
    assert status == "ok" and labeller.replans == 1
    assert labels.tolist() == positions_to_actions(plan[1:3])[0].tolist()
    # one agent did not take its planned move (it stayed where it was): the state left the plan
    moved = [i for i in range(inst.num_agents)
             if (plan[2, i] != plan[1, i]).any()
             and not (plan[2] == plan[1, i]).all(axis=1).any()]
    assert moved, "the instance needs an agent whose left cell stays free"
    off = plan[2].copy()
    off[moved[0]] = plan[1, moved[0]]
    labels, status = labeller.label(_state(inst, off, 2))
    assert labeller.replans == 2 and status == "ok"
    replanned = labeller.expert.keeper.remaining_plan()
    assert (replanned[0] == off).all()
    assert labels.tolist() == positions_to_actions(replanned[:2])[0].tolist()
    # a new episode (step 0) starts a new expert
    labeller.label(_state(inst, inst.starts, 0))
    assert labeller.replans == 3


def test_committed_is_selectable_in_the_config():
    cfg = dagger.config_from_dict({"labeller": "committed", "committed_budget": 0.5,
                                   "committed_replan_every": 8,
                                   "conflict_rule": "pibt_anchor_swap", "ranking": "q"})
    assert cfg.conflict_rule == "pibt_anchor_swap" and cfg.ranking == "q"
    labeller = dagger.make_labeller(cfg)
    assert isinstance(labeller, CommittedLabeller)
    assert (labeller.planning_budget, labeller.replan_every) == (0.5, 8)
    assert dagger.make_labeller(cfg, seed=7).seed == 7
    assert isinstance(dagger.make_labeller(dagger.config_from_dict({})), dagger.LaCAMLabeller)
    with pytest.raises(dagger.DaggerConfigError, match="'labeller' = 'fresh'"):
        dagger.config_from_dict({"labeller": "fresh"}, source="x.yaml")
    with pytest.raises(dagger.DaggerConfigError, match="committed_budget"):
        dagger.config_from_dict({"committed_budget": 0}, source="x.yaml")


def _tiny_ceiling(tmp_path, labeller):
    path = tmp_path / f"{labeller}.yaml"
    path.write_text(yaml.safe_dump({
        "conflict_rule": "pibt_anchor_swap", "labeller": labeller, "label_time_limit": 1.0,
        "committed_budget": 1.0,
        "ceiling": [{"kind": "random", "size": 9, "agents": [3, 5], "max_steps": 32}],
        "ceiling_lifelong": [{"kind": "random", "size": 9, "agents": [3], "max_steps": 12}],
        "ceiling_count": 3, "ceiling_agreement_episodes": 2}))
    return path


@pytest.mark.parametrize("labeller", ["committed", "lacam"])
def test_expert_ceiling_command(tmp_path, capsys, labeller):
    out = tmp_path / "ceiling.json"
    rc = dagger.main(["--expert-ceiling", "--config", str(_tiny_ceiling(tmp_path, labeller)),
                      "--count", "2", "--json", str(out)])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "| random 9x9 | 5 | 1.00 |" in printed and "lifelong" in printed
    result = json.loads(out.read_text())
    assert result["labeller"] == labeller and result["rule"] == "pibt_anchor_swap"
    rows = result["one_shot"]
    assert [(r["agents"], r["instances"]) for r in rows] == [(3, 2), (5, 2)]
    for row in rows:
        # a few agents on a 9x9 map: both solve every instance, and the labeller labels
        assert row["pibt_success"] == 1.0 and row["expert_success"] == 1.0
        assert row["success_at_most"] == 1.0 and row["unsolvable"] == []
        assert 0.0 <= row["self_agreement"] <= 1.0 and row["agreement_labels"] > 0
        assert row["label_cpu_s_per_state"] > 0 and row["plans_per_episode"] >= 1
    # plain PIBT's column is the held-out baseline's rollout on the same instances
    task = {"kind": "random", "size": 9, "max_steps": 32}
    plain = [dagger.play_plain_pibt(inst, 32, "pibt_anchor_swap")
             for inst in ceiling.ceiling_instances(task, 5, 2, 0)]
    assert rows[1]["pibt_steps"] == np.mean([p["steps"] for p in plain])
    (life,) = result["lifelong"]
    assert life["pibt_throughput"] > 0 and life["expert_throughput"] > 0


def test_expert_ceiling_errors_name_the_option(tmp_path, capsys):
    assert dagger.main(["--expert-ceiling"]) == 2
    assert "--expert-ceiling needs --config" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("labeller: fresh\n")
    assert dagger.main(["--expert-ceiling", "--config", str(bad)]) == 2
    assert f"{bad}: field 'labeller' = 'fresh'" in capsys.readouterr().err


def test_the_labeller_as_the_policy_follows_its_labels():
    """beta 1, every state labelled: the executed moves are the labels wherever the rule lets
    them through; with no network the unlabelled ranking is plain PIBT's."""
    inst = generate_instance(10, 4, 0.1, 2)
    labeller = CommittedLabeller(planning_budget=2.0)
    out = dagger.play_episode(None, inst, 40, "pibt_anchor_swap", "distance", None, labeller,
                              beta=1.0, record=False)
    assert out["success"] and out["expert_steps"] == out["label_calls"] == out["steps"]
    assert labeller.replans >= 1
    with pytest.raises(ValueError, match="record=False"):
        dagger.play_episode(None, inst, 40, "pibt", "distance", None)


def test_stuck_labels_only_from_the_state_where_progress_stopped():
    inst = generate_instance(10, 6, 0.1, 5)
    labeller = StuckLabeller(planning_budget=2.0, window=3)
    # progress (the summed distance falls) and then none: skipped until 3 states without a low
    plan = CommittedLabeller(2.0)
    plan.label(_state(inst, inst.starts, 0))
    path = plan.expert.keeper.plan
    assert labeller.label(_state(inst, inst.starts, 0)).status == "skipped"
    assert labeller.label(_state(inst, path[1], 1)).status == "skipped"
    for step in (2, 3):
        labels, status = labeller.label(_state(inst, path[1], step))
        assert status == "skipped" and (labels == -1).all() and labeller.active_from is None
    labels, status = labeller.label(_state(inst, path[1], 4))
    assert status == "ok" and (labels >= 0).all() and labeller.active_from == 4
    # from there on, the committed expert's plan from the stuck state
    kept = labeller.committed.expert.keeper.remaining_plan()
    assert (kept[0] == path[1]).all()
    assert labels.tolist() == positions_to_actions(kept[:2])[0].tolist()
    assert labeller.label(_state(inst, kept[1], 5)).status == "ok" and labeller.replans == 1
    # a new episode waits for progress to stop again
    assert labeller.label(_state(inst, inst.starts, 0)).status == "skipped"
    cfg = dagger.config_from_dict({"labeller": "stuck", "stuck_window": 5})
    assert dagger.make_labeller(cfg).window == 5


def test_kept_pymapf_plan_labels_its_next_moves_and_replans_off_it():
    inst = generate_instance(10, 6, 0.1, 5)
    cfg = dagger.config_from_dict({"labeller": "committed", "committed_planner": "pymapf",
                                   "committed_budget": 2.0})
    labeller = dagger.make_labeller(cfg)
    assert isinstance(labeller, KeptPyMAPFLabeller)
    labels, status = labeller.label(_state(inst, inst.starts, 0))
    plan = labeller.plan.copy()
    assert status == "ok" and labeller.replans == 1
    assert labels.tolist() == positions_to_actions(plan[:2])[0].tolist()
    labels, _ = labeller.label(_state(inst, plan[1], 1))
    assert labeller.replans == 1 and labels.tolist() == positions_to_actions(plan[1:3])[0].tolist()
    # the same state again (the rule refused the step): off the plan, planned afresh
    labeller.label(_state(inst, plan[1], 2))
    assert labeller.replans == 2 and (labeller.plan[0] == plan[1]).all()
    with pytest.raises(dagger.DaggerConfigError, match="committed_planner"):
        dagger.config_from_dict({"committed_planner": "cbs"})


def test_a_dagger_round_with_the_committed_labeller(tmp_path):
    """`labeller: committed` runs a round end to end: its labels land in the shards and train."""
    import torch

    from mapf_fleet.models.checkpoint import build_model, save_checkpoint
    from mapf_fleet.models.config import ModelConfig

    torch.manual_seed(0)
    init = tmp_path / "small.pt"
    save_checkpoint(init, build_model(ModelConfig.preset("dcc", "small")),
                    {"alpha": 0.0, "curriculum": {}, "learner_steps": 0, "training_config": {}})
    cfg = dagger.config_from_dict({
        "init_checkpoint": str(init), "labeller": "committed", "committed_budget": 1.0,
        "conflict_rule": "pibt_anchor_swap", "rounds": 1, "episodes_per_round": 2,
        "use_ray": False, "late_tasks": [], "heldout_count": 2, "updates_per_round": 2,
        "batch_windows": 2, "seq_len": 6, "burn_in": 3, "device": "cpu",
        "tasks": [{"kind": "random", "size": 9, "agents": [4], "weight": 1.0, "max_steps": 24}],
        "heldout": [{"kind": "random", "size": 9, "agents": 3, "max_steps": 24}]})
    run = tmp_path / "run"
    dagger.Dagger(cfg, run, log=lambda m: None).run()
    manifest = json.loads((run / "data" / "manifest.json").read_text())
    assert sum(m["labels"] for m in manifest["shards"].values()) > 0
    arrays, _ = dagger.read_shard(run / "data" / "r000_e000.npz")
    assert (arrays["labels"] >= 0).any()
    assert (run / "checkpoints" / "round_000.pt").is_file()


def test_the_shipped_ceiling_configs_load():
    from pathlib import Path

    configs = Path(__file__).resolve().parents[1] / "config" / "training"
    cfg = dagger.load_config(configs / "dagger_committed.yaml")
    assert (cfg.labeller, cfg.conflict_rule) == ("committed", "pibt_anchor_swap")
    dense = dagger.load_config(configs / "experiments" / "dagger_ceiling_dense_pymapf.yaml")
    assert (dense.labeller, dense.committed_planner) == ("committed", "pymapf")


def test_self_agreement_labeller_shares_no_search_seed(monkeypatch):
    # with k searches per re-plan the labeller uses seeds s .. s + k - 1; a second labeller at
    # s + 1 would repeat k - 1 of its searches and agree with it by construction
    cfg = dagger.config_from_dict({
        "conflict_rule": "pibt_anchor_swap", "labeller": "committed", "committed_budget": 1.0,
        "committed_restarts": 3, "planner_seed": 5, "ceiling_agreement_episodes": 1})
    seeds = []
    real = ceiling.make_labeller

    def spy(config, seed=None):
        seeds.append(config.planner_seed if seed is None else seed)
        return real(config, seed=seed)

    monkeypatch.setattr(ceiling, "make_labeller", spy)
    row = ceiling.one_shot_row(cfg, {"kind": "random", "size": 9, "max_steps": 32}, 3, 1)
    assert seeds == [5, 8] and row["agreement_labels"] > 0
