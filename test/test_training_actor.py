"""The actor: Eq. 2 applied to the environment's rewards, epsilon schedule, sequences out."""

import numpy as np
import pytest
import torch

from mapf_fleet.training.actor import EpisodeWorker, Task
from mapf_fleet.training.config import TrainConfig


def _cfg(**kw):
    base = dict(model_preset="small", num_actors=2, envs_per_actor=2, max_episode_steps=12,
                seq_len=4, burn_in=2, final_agents=6, final_map_size=10, obstacle_density=0.0,
                explore_all_agents=True)
    base.update(kw)
    return TrainConfig(**base)


def _eq2_by_hand(rewards, positions, alpha):
    out = np.empty(len(rewards))
    for i in range(len(rewards)):
        near = [j for j in range(len(rewards)) if j != i
                and abs(positions[j][0] - positions[i][0]) <= 4
                and abs(positions[j][1] - positions[i][1]) <= 4]
        out[i] = rewards[i] if not near else \
            (1 - alpha) * rewards[i] + alpha * np.mean([rewards[j] for j in near])
    return out


def test_actor_rewards_follow_eq2_with_task_alpha():
    torch.manual_seed(0)
    worker = EpisodeWorker(_cfg(), actor_index=0, seed=3)  # epsilon 0.4: varied rewards
    worker.keep_records = True
    worker.set_task(Task(num_agents=6, map_size=10, alpha=0.5))
    result = worker.run(40)
    assert worker.records and len(result["episodes"]) == len(worker.records)
    differs = False
    for rec in worker.records:
        for t in range(rec.length):
            expected = _eq2_by_hand(rec.individual_rewards[t], rec.positions[t + 1], 0.5)
            np.testing.assert_allclose(rec.rewards[t], expected, rtol=1e-5, atol=1e-6)
            differs |= not np.allclose(rec.rewards[t], rec.individual_rewards[t])
    assert differs, "6 agents on 10x10 always have FOV neighbours with different rewards"
    # sequences carry all 6 agents and the n-step sums of the shaped rewards
    seq = result["sequences"][0]
    assert seq["actions"].shape == (4, 6) and seq["hidden"].shape[0] == 6
    rec = worker.records[0]
    r = rec.rewards
    np.testing.assert_allclose(seq["returns"][0], r[0] + 0.99 * r[1], rtol=1e-5)


def test_alpha_zero_keeps_individual_rewards():
    worker = EpisodeWorker(_cfg(), actor_index=0, seed=4)
    worker.keep_records = True
    worker.set_task(Task(num_agents=4, map_size=10, alpha=0.0))
    worker.run(12)
    for rec in worker.records:
        np.testing.assert_allclose(rec.rewards, rec.individual_rewards)


def test_epsilon_schedule_and_gate_actors():
    cfg = TrainConfig(num_actors=4)
    eps = [cfg.actor_epsilon(i) for i in range(4)]
    np.testing.assert_allclose(eps, [0.4 ** (1 + 7 * i / 3) for i in range(4)])
    assert cfg.gate_actor_indices() == [2, 3]
    assert TrainConfig(num_actors=1).gate_actor_indices() == [0]


def test_task_change_drops_running_episodes():
    worker = EpisodeWorker(_cfg(), actor_index=1, seed=5)
    worker.set_task(Task(2, 10, 0.0, version=0))
    worker.run(3)
    assert worker.envs
    worker.set_task(Task(3, 10, 0.0, version=1))
    assert worker.envs == []
    result = worker.run(12)
    assert all(ep["num_agents"] == 3 and ep["task_version"] == 1 for ep in result["episodes"])


def test_per_env_epsilons_cover_the_schedule_and_gate_the_least_exploring():
    cfg = TrainConfig(num_actors=2, envs_per_actor=4, epsilon_per_env=True)
    assert cfg.num_explorers == 8
    eps = sorted(cfg.slot_epsilon(a, k) for a in range(2) for k in range(4))
    np.testing.assert_allclose(eps, sorted(0.4 ** (1 + 7 * i / 7) for i in range(8)))
    gate = {(a, k) for a in range(2) for k in range(4) if cfg.is_gate_slot(a, k)}
    assert len(gate) == 4
    assert max(cfg.slot_epsilon(a, k) for a, k in gate) < \
        min(cfg.slot_epsilon(a, k) for a in range(2) for k in range(4) if (a, k) not in gate)
    # interleaved: each actor holds exploring and gate slots
    assert {a for a, _ in gate} == {0, 1}
    paper = TrainConfig(num_actors=4, envs_per_actor=3, epsilon_per_env=False)
    assert paper.slot_epsilon(2, 0) == paper.slot_epsilon(2, 2) == paper.actor_epsilon(2)
    worker = EpisodeWorker(_cfg(envs_per_actor=4, num_actors=1), actor_index=0, seed=1)
    worker.set_task(Task(1, 10, 0.0))
    result = worker.run(40)
    assert {ep["gate"] for ep in result["episodes"]} <= {True, False}
    assert all(ep["gate"] == (ep["epsilon"] <= np.median(worker.epsilons))
               for ep in result["episodes"])


def test_step_limit_grows_with_the_curriculum_map():
    cfg = TrainConfig(max_steps_per_map_side=6.4)
    assert [cfg.episode_step_limit(s) for s in (10, 15, 40, 80)] == [64, 96, 256, 256]
    assert TrainConfig().episode_step_limit(10) == 256
    worker = EpisodeWorker(_cfg(max_episode_steps=256, max_steps_per_map_side=1.0), 0, seed=2)
    worker.set_task(Task(2, 10, 0.0))
    result = worker.run(25)
    assert result["episodes"] and all(ep["steps"] <= 10 for ep in result["episodes"])


@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_shielded_actor_records_the_executed_actions(algo):
    """conflict_rule: pibt (and pibt_anchor): every recorded step is the action that moved the agent (the
    learner trains on what was executed), and no move collides; without the shield random
    weights collide."""
    from mapf_fleet.grid.actions import ACTION_DELTAS

    def play(rule):
        torch.manual_seed(0)
        worker = EpisodeWorker(_cfg(algo=algo, conflict_rule=rule, final_agents=10), actor_index=0, seed=5)
        worker.keep_records = True
        worker.set_task(Task(num_agents=10, map_size=10, alpha=0.0))
        worker.run(36)
        return worker.records

    collisions = 0
    for rec in play("pibt") + play("pibt_anchor"):
        moved = rec.positions[1:].astype(np.int64) - rec.positions[:-1].astype(np.int64)
        np.testing.assert_array_equal(moved, ACTION_DELTAS[rec.actions.astype(np.int64)])
        # the collision penalty (-0.5) never appears in the individual rewards
        collisions += int((rec.individual_rewards <= -0.5).sum())
    assert collisions == 0
    unshielded = play("revert")
    assert sum(int((r.individual_rewards <= -0.5).sum()) for r in unshielded) > 0


@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_replay_action_preferred_trains_first_choices_and_feeds_executed_last_actions(algo):
    """replay_action: preferred: the replay's action is each agent's own first choice (greedy,
    agent 0 possibly exploring), the executed one moved it, and the sequences' last-action
    input is the executed action. Overridden first choices exist (random weights, 10 agents)."""
    from mapf_fleet.grid.actions import ACTION_DELTAS
    from mapf_fleet.training.episodes import episode_to_sequences

    torch.manual_seed(0)
    cfg = _cfg(algo=algo, conflict_rule="pibt", replay_action="preferred", final_agents=10)
    worker = EpisodeWorker(cfg, actor_index=0, seed=5)
    worker.keep_records = True
    worker.set_task(Task(num_agents=10, map_size=10, alpha=0.0))
    worker.run(36)
    assert worker.records
    overridden = 0
    for rec in worker.records:
        assert rec.executed_actions is not None
        moved = rec.positions[1:].astype(np.int64) - rec.positions[:-1].astype(np.int64)
        np.testing.assert_array_equal(moved,
                                      ACTION_DELTAS[rec.executed_actions.astype(np.int64)])
        overridden += int((rec.actions != rec.executed_actions).sum())
        assert int((rec.individual_rewards <= -0.5).sum()) == 0
        seq = episode_to_sequences(rec, cfg.seq_len, cfg.burn_in, cfg.n_step, cfg.gamma)[0]
        steps = min(rec.length, cfg.seq_len + cfg.n_step) - 1
        np.testing.assert_array_equal(seq["last_actions"][cfg.burn_in + 1:cfg.burn_in + 1 + steps],
                                      rec.executed_actions[:steps])
        np.testing.assert_array_equal(seq["actions"][:min(rec.length, cfg.seq_len)],
                                      rec.actions[:cfg.seq_len])
    assert overridden > 0
    with pytest.raises(Exception, match="replay_action"):
        _cfg(replay_action="both")


def test_conflict_rule_config_is_validated():
    from mapf_fleet.training.config import TrainConfigError

    with pytest.raises(TrainConfigError, match="conflict_rule"):
        _cfg(conflict_rule="cbs")
    with pytest.raises(TrainConfigError, match="ranking"):
        _cfg(ranking="distance")


def test_init_checkpoint_starts_the_run_from_its_weights(tmp_path):
    from mapf_fleet.models.checkpoint import CheckpointError, save_checkpoint
    from mapf_fleet.training.modelio import build_model
    from mapf_fleet.training.trainer import Trainer

    cfg = _cfg(use_ray=False) if "use_ray" in TrainConfig.__dataclass_fields__ else _cfg()
    torch.manual_seed(11)
    source = build_model(cfg)
    path = save_checkpoint(tmp_path / "init.pt", source, {"alpha": 0.0, "curriculum": {},
                                                          "learner_steps": 0, "training_config": {}})
    trainer = Trainer(cfg.replace(init_checkpoint=str(path)), tmp_path / "run")
    for name, value in source.state_dict().items():
        assert torch.equal(trainer.learner.model.state_dict()[name], value), name
        assert torch.equal(trainer.learner.target.state_dict()[name], value), name
    other = cfg.replace(algo="dcc", init_checkpoint=str(path))
    with pytest.raises(CheckpointError, match="init.pt: init_checkpoint is a dhc network"):
        Trainer(other, tmp_path / "run2")
