"""TrainConfig.task_mix: the actors draw every episode from the mix (kinds, sizes, agent counts),
the step limit follows the drawn map, the mix's agents fit the replay, and a run trains on it."""

import numpy as np
import pytest
import torch

from pathlib import Path

from mapf_fleet.grid.maps import TaskMix, sample_task_instance
from mapf_fleet.training.actor import EpisodeWorker, Task
from mapf_fleet.training.config import TrainConfig, TrainConfigError, config_from_dict, load_config
from mapf_fleet.training.curriculum import ScaleCurriculum

CONFIGS = Path(__file__).resolve().parent.parent / "config" / "training"
MIX = {"kinds": {"maze": 1, "rooms": 1}, "sizes": [8, 10], "agents": [1, 2, 3]}


def _cfg(**kw):
    base = dict(model_preset="small", num_actors=1, envs_per_actor=4, seq_len=4, burn_in=0,
                final_agents=3, final_map_size=10, max_episode_steps=256,
                max_steps_per_map_side=2.0, task_mix=MIX)
    base.update(kw)
    return TrainConfig(**base)


def _play(algo: str, seed: int, steps: int = 60):
    torch.manual_seed(0)
    worker = EpisodeWorker(_cfg(algo=algo), actor_index=0, seed=seed)
    worker.set_task(Task(num_agents=1, map_size=40, alpha=0.0))  # the setting is not used
    first = worker.run(0)  # creates the environments: the first draws of the worker's rng
    assert first["episodes"] == []
    instances = [e["env"].instance for e in worker.envs]
    result = worker.run(steps)
    return instances, result


@pytest.mark.parametrize("algo", ["dhc", "dcc"])
def test_actor_episodes_are_drawn_from_the_mix(algo):
    instances, result = _play(algo, seed=7)
    # the environments hold the mix's first draws from the same seeded rng, in slot order
    rng = np.random.default_rng(7)
    expected = [sample_task_instance(TaskMix.from_dict(MIX), rng) for _ in instances]
    assert instances == [d.instance for d in expected]
    episodes = result["episodes"]
    assert len(episodes) >= 8
    cfg = _cfg()
    for ep in episodes:
        assert ep["map_kind"] in ("maze", "rooms")
        assert ep["map_size"] in (8, 10) and ep["num_agents"] in (1, 2, 3)
        # the step limit is the drawn map's: ceil(2.0 x side), not the task's 40x40
        assert ep["steps"] <= cfg.episode_step_limit(ep["map_size"])
    assert {ep["map_kind"] for ep in episodes} == {"maze", "rooms"}
    assert {ep["map_size"] for ep in episodes} == {8, 10}
    assert len({ep["num_agents"] for ep in episodes}) >= 2  # mixed counts in one batch
    timed_out = {ep["map_size"] for ep in episodes if not ep["success"]}
    assert all(ep["steps"] == cfg.episode_step_limit(ep["map_size"])
               for ep in episodes if not ep["success"]) and timed_out
    # one replay sequence per 4 steps of every agent, as wide as the episode's agents
    assert all(s["actions"].shape[1] in (1, 2, 3) for s in result["sequences"])
    # seeded: the same worker seed plays the same episodes
    again_instances, again = _play(algo, seed=7)
    assert again_instances == instances
    assert [(e["map_kind"], e["map_size"], e["num_agents"], e["steps"], e["success"])
            for e in again["episodes"]] == \
        [(e["map_kind"], e["map_size"], e["num_agents"], e["steps"], e["success"])
         for e in episodes]


def test_grouped_forward_matches_one_environment_at_a_time():
    """Environments with different agent counts are stepped per count; each one's Q-values
    are those of the network run on that environment alone."""
    from mapf_fleet.training.modelio import model_step

    torch.manual_seed(0)
    worker = EpisodeWorker(_cfg(algo="dcc", envs_per_actor=6), actor_index=0, seed=3)
    worker.set_task(Task(1, 10, 0.0))
    worker.run(5)
    envs = worker.envs
    assert len({e["env"].num_agents for e in envs}) >= 2
    greedy, q, hidden = worker._forward(envs)
    for slot, e in enumerate(envs):
        env = e["env"]
        with torch.no_grad():
            out = model_step(worker.model, "dcc", torch.from_numpy(e["obs"][None]),
                             torch.from_numpy(env.positions[None].astype(np.int64)),
                             torch.from_numpy(e["hidden"][None]),
                             torch.from_numpy(env.last_actions[None].astype(np.int64)))
        np.testing.assert_allclose(q[slot], out.q[0].numpy(), atol=1e-5)
        np.testing.assert_allclose(hidden[slot], out.hidden[0].numpy(), atol=1e-5)
        np.testing.assert_array_equal(greedy[slot, :env.num_agents], out.q[0].argmax(-1).numpy())
        assert not greedy[slot, env.num_agents:].any()


def test_mix_agents_above_final_agents_are_rejected_naming_the_field():
    with pytest.raises(TrainConfigError) as err:
        config_from_dict({"task_mix": MIX, "final_agents": 2}, source="mix.yaml")
    text = str(err.value)
    assert "mix.yaml: field 'task_mix'" in text and "3 agents exceed final_agents (2)" in text
    assert _cfg(final_agents=3).task_mix == MIX


def test_single_gate_scale_curriculum_jumps_to_the_final_setting():
    cur = ScaleCurriculum(1, 10, 12, 40, 5, window=4, threshold=0.5, single_gate=True)
    assert not any(cur.record(s) for s in [True, False, False])
    assert not any(cur.record(True) for _ in range(2))  # 2/4 is not above 0.5
    assert cur.setting == (1, 10)
    assert cur.record(True) and cur.done and cur.setting == (12, 40)  # 3/4
    assert cur.transitions == 1


def test_short_train_run_on_a_mix_passes_both_gates(tmp_path):
    """In-process actors on maze+rooms: stage 1 is one gate on mix tasks, stage 2 (one fixed
    alpha) runs on them too; the checkpoints record the mix."""
    from mapf_fleet.models.checkpoint import load_checkpoint
    from mapf_fleet.training.trainer import Trainer

    cfg = load_config(CONFIGS / "tiny.yaml").replace(
        use_ray=False, num_actors=1, envs_per_actor=4, actor_steps_per_call=16, batch_size=4,
        seq_len=4, burn_in=0, learning_starts=40, demo_source="none", final_agents=2,
        final_map_size=10, task_mix={"kinds": {"maze": 1, "rooms": 1}, "sizes": [8, 10],
                                     "agents": [1, 2]},
        max_steps_per_map_side=2.0, success_window=4, success_threshold=0.0,
        alpha_mode="fixed", fixed_alpha=0.5, alpha_min_updates=3, alpha_max_updates=200,
        max_updates=200, max_wall_seconds=20.0, state_interval_updates=1000)
    result = Trainer(cfg, tmp_path / "run").run()
    assert result["finished"], result
    assert result["alpha_passed"] == [0.5]
    assert any("stage 1: the training mix passed the gate" in e for e in result["events"])
    assert result["learner_updates"] >= 3
    assert {"stage1.pt", "alpha_0.5.pt", "final.pt"} <= set(result["checkpoints"])
    _, meta = load_checkpoint(tmp_path / "run" / "checkpoints" / "final.pt")
    assert meta["curriculum"]["task_mix"]["kinds"] == {"maze": 1, "rooms": 1}


def test_sample_config_dcc_mix_loads():
    cfg = load_config(CONFIGS / "experiments" / "dcc_mix.yaml")
    mix = TaskMix.from_dict(cfg.task_mix)
    assert cfg.algo == "dcc" and set(mix.kinds) == {"random", "maze", "rooms", "warehouse"}
    assert max(mix.sizes) >= 40 and max(mix.agents) == 64 <= cfg.final_agents
    assert Path(CONFIGS.parent.parent / cfg.init_checkpoint).is_file()
