"""The evaluator's side of DAgger's rankings: the `confidence` ranking, the default ranking
per conflict rule, and the evaluator's `--kinds dense` scenarios."""

from __future__ import annotations

import numpy as np
import pytest

from mapf_fleet.coordination.ranking import (DEFAULT_RANKING_BY_RULE, default_ranking,
                                             rank_actions)
from mapf_fleet.grid.actions import DOWN, LEFT, RIGHT, STAY, UP
from mapf_fleet.grid.env import MAPFEnv
from mapf_fleet.grid.instance import Instance


def test_confidence_puts_the_argmax_first_only_when_it_leads():
    grid = np.zeros((5, 5), dtype=np.uint8)
    obs = MAPFEnv(Instance(grid, np.array([[2, 2]]), np.array([[0, 2]]))).reset()  # goal up
    q = np.array([[3.0, 2.0, 1.0, 2.5, 0.0]])  # stay leads left by 0.5
    assert rank_actions(obs, q, "confidence", margin=0.4)[0].tolist() == \
        rank_actions(obs, q, "q_then_distance")[0].tolist() == [STAY, UP, LEFT, DOWN, RIGHT]
    # not sure enough: the distance order (closer, stay, then away moves by Q)
    assert rank_actions(obs, q, "confidence", margin=0.6)[0].tolist() == \
        [UP, STAY, LEFT, DOWN, RIGHT]
    # per agent: one sure, one not
    both = np.concatenate([obs, obs])
    qs = np.array([[3.0, 2.0, 1.0, 2.5, 0.0], [3.0, 2.0, 1.0, 2.95, 0.0]])
    ranked = rank_actions(both, qs, "confidence", margin=0.1)
    assert ranked[:, 0].tolist() == [STAY, UP]


def test_default_ranking_follows_the_conflict_rule():
    from mapf_fleet.evaluation.policies import parse_policy, with_conflict_rule

    assert default_ranking("pibt_anchor") == "confidence" and default_ranking("pibt") == "q"
    spec = parse_policy("heuristic")
    assert with_conflict_rule(spec, "pibt_anchor").resolved_ranking == "distance"
    from mapf_fleet.evaluation.policies import PolicySpec

    learned = PolicySpec("checkpoint", "x", path="x.pt")
    for rule, mode in DEFAULT_RANKING_BY_RULE.items():
        assert with_conflict_rule(learned, rule).resolved_ranking == mode
    # an explicit --ranking wins
    assert with_conflict_rule(learned, "pibt_anchor", "q").resolved_ranking == "q"


def _checkpoint(path, **metadata):
    import torch

    from mapf_fleet.models.checkpoint import build_model, save_checkpoint
    from mapf_fleet.models.config import ModelConfig

    torch.manual_seed(0)
    return str(save_checkpoint(path, build_model(ModelConfig.preset("dhc", "small")), {
        "alpha": 0.0, "curriculum": {}, "learner_steps": 0, "training_config": {}, **metadata}))


def test_a_checkpoints_recorded_ranking_is_its_default_and_an_asked_ranking_beats_it(tmp_path):
    """Precedence: --ranking > the checkpoint's `rankings` for the rule > the rule's."""
    from mapf_fleet.evaluation.policies import build_policy, parse_policy, with_conflict_rule

    assert default_ranking("pibt_anchor", {"pibt_anchor": "q_then_distance"}) == "q_then_distance"
    assert default_ranking("pibt", {"pibt_anchor": "q_then_distance"}) == default_ranking("pibt")
    spec = parse_policy(_checkpoint(tmp_path / "round_007.pt",
                                    rankings={"pibt_anchor": "q_then_distance"}))
    anchored = with_conflict_rule(spec, "pibt_anchor")
    assert anchored.resolved_ranking == "q_then_distance"
    assert anchored.name == "round_007 +PIBT-anchor(q_then_distance)"  # which ranking ran
    assert build_policy(anchored).ranking == "q_then_distance"
    plain = with_conflict_rule(spec, "pibt")  # no ranking recorded for this rule: the rule's
    assert (plain.resolved_ranking, plain.name) == (default_ranking("pibt"), "round_007 +PIBT")
    asked = with_conflict_rule(spec, "pibt_anchor", "confidence")
    assert (asked.resolved_ranking, asked.name) == ("confidence",
                                               "round_007 +PIBT-anchor(confidence)")
    # a checkpoint without rankings keeps the rule's default, unnamed as before
    old = with_conflict_rule(parse_policy(_checkpoint(tmp_path / "old.pt")), "pibt_anchor")
    assert (old.resolved_ranking, old.name) == (default_ranking("pibt_anchor"), "old +PIBT-anchor")


def test_evaluate_dense_scenarios():
    from mapf_fleet.evaluation.cli import dense_scenarios
    from mapf_fleet.evaluation.protocol import ProtocolError

    (scenario, instances), = dense_scenarios(3, 7, [21], [32])
    assert scenario.max_steps == 128 and scenario.num_agents == 32
    assert instances.maps.shape == (3, 21, 21)
    again = dense_scenarios(2, 7, [21], [32])[0][1]
    assert (again.maps == instances.maps[:2]).all()  # a prefix is the same instances
    with pytest.raises(ProtocolError, match="do not fit"):
        dense_scenarios(1, 7, [12], [64])
