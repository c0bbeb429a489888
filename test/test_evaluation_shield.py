"""The evaluator under the coordination layer (`--conflict-rule pibt`)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mapf_fleet.evaluation.cli import main as evaluate_main
from mapf_fleet.evaluation.policies import CheckpointBatchPolicy
from mapf_fleet.evaluation.protocol import InstanceSet
from mapf_fleet.evaluation.runner import run_decentralized
from mapf_fleet.grid.instance import generate_instance


def _instances(size, agents, count, seed=0):
    insts = [generate_instance(size, agents, 0.2, seed + k) for k in range(count)]
    return InstanceSet(np.stack([i.grid for i in insts]), np.stack([i.starts for i in insts]),
                       np.stack([i.goals for i in insts]), "generated")


@pytest.fixture(scope="module")
def dcc_checkpoint(tmp_path_factory):
    import torch

    from mapf_fleet.models.checkpoint import build_model, save_checkpoint
    from mapf_fleet.models.config import ModelConfig
    from mapf_fleet.models.synthetic import make_sensitive

    torch.manual_seed(1)
    model = build_model(ModelConfig.preset("dcc", "small"))
    make_sensitive(model, seed=3)
    path = tmp_path_factory.mktemp("ckpt") / "dcc.pt"
    return str(save_checkpoint(path, model, {"alpha": 0.0, "curriculum": {}, "learner_steps": 0,
                                             "training_config": {}}))


class RecordingPolicy(CheckpointBatchPolicy):
    """Records the last actions the network reads at each step, and what was executed."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.seen_last, self.executed_log = [], []

    def act(self, obs, positions):
        self.seen_last.append(self.policy.last_actions.cpu().numpy().copy())
        return super().act(obs, positions)

    def executed(self, actions):
        self.executed_log.append(np.asarray(actions).copy())
        super().executed(actions)


def test_shielded_episodes_have_no_collision_and_dcc_sees_the_executed_action(dcc_checkpoint):
    instances = _instances(10, 12, 3)
    policy = RecordingPolicy(dcc_checkpoint, "cpu", "q")
    records = run_decentralized(policy, instances, 24, conflict_rule="pibt")
    assert sum(r.collisions for r in records) == 0
    assert sum(r.overrides for r in records) > 0  # random weights: the shield had work to do
    # while no episode has ended, the last-action input at step t+1 is what ran at step t
    steps = min(len(policy.executed_log), len(policy.seen_last) - 1)
    compared = 0
    for t in range(steps):
        if policy.seen_last[t + 1].shape == policy.executed_log[t].shape:
            assert (policy.seen_last[t + 1] == policy.executed_log[t]).all()
            compared += 1
    assert compared > 5
    unshielded = run_decentralized(CheckpointBatchPolicy(dcc_checkpoint), instances, 24)
    assert sum(r.overrides for r in unshielded) == 0


def test_evaluate_cli_shield_rows(tmp_path, dcc_checkpoint):
    out = tmp_path / "eval.json"
    code = evaluate_main(["--checkpoint", dcc_checkpoint, "heuristic", "--no-references",
                          "--conflict-rule", "revert", "pibt", "--sizes", "40", "--agents", "8",
                          "--instances", "4", "--max-steps", "40", "--quiet", "--json", str(out),
                          "--guidance", "none"])  # the rows' labels without a guidance suffix
    assert code == 0
    rows = {r["policy"]: r for r in json.loads(out.read_text())["results"]}
    assert set(rows) == {"dcc", "dcc +PIBT", "heuristic", "heuristic +PIBT"}
    for name in ("dcc +PIBT", "heuristic +PIBT"):
        assert rows[name]["collisions"] == 0
        assert all(e["collisions"] == 0 for e in rows[name]["episodes"])
    assert rows["heuristic"]["overrides"] == 0
    meta = {p["name"]: p for p in json.loads(out.read_text())["metadata"]["policies"]}
    assert meta["dcc +PIBT"]["conflict_rule"] == "pibt" and meta["dcc +PIBT"]["ranking"] == "q"
    assert meta["heuristic +PIBT"]["ranking"] == "distance"


def test_evaluate_cli_rankings(tmp_path, dcc_checkpoint, capsys):
    code = evaluate_main(["--checkpoint", dcc_checkpoint, "--no-references", "--conflict-rule", "pibt",
                          "--ranking", "q", "q_demote_stay", "--sizes", "40", "--agents", "4",
                          "--instances", "2", "--max-steps", "10", "--quiet"])
    assert code == 0
    text = capsys.readouterr().out
    assert "dcc +PIBT(q)" in text and "dcc +PIBT(q_demote_stay)" in text
