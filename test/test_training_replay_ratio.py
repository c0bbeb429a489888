"""`max_replay_ratio`: the learner waits for the actors instead of reusing samples without bound."""

from pathlib import Path

import pytest

from mapf_fleet.training.config import TrainConfigError, load_config
from mapf_fleet.training.trainer import Trainer

CONFIGS = Path(__file__).resolve().parent.parent / "config" / "training"


def _short(**changes):
    # in-process actors, no warm start, stage 2 at once on a small task, a fixed update budget
    return load_config(CONFIGS / "tiny.yaml").replace(
        use_ray=False, num_actors=1, envs_per_actor=2, actor_steps_per_call=8,
        demo_source="none", start_agents=2, start_map_size=10, final_agents=2,
        final_map_size=10, alpha_mode="fixed", fixed_alpha=0.0, success_threshold=1.0,
        plateau_windows=0, learning_starts=50, batch_size=8, max_updates=40,
        max_wall_seconds=300, progress_bar=False, **changes)


def test_learner_keeps_sampled_over_added_sequences_within_the_limit(tmp_path):
    result = Trainer(_short(max_replay_ratio=0.5), tmp_path / "limited").run()
    counters = result["counters"]
    # the budget is reached: the learner waited for sequences, it did not stop
    assert result["learner_updates"] == 40, result["stop_reason"]
    assert counters["sampled_sequences"] == 40 * 8
    assert counters["sampled_sequences"] <= 0.5 * counters["added_sequences"]


def test_without_a_limit_the_learner_outruns_the_actors(tmp_path):
    """The failure the limit is for: with one small actor the learner samples each added
    sequence several times (the same run as above, no limit)."""
    result = Trainer(_short(max_replay_ratio=0.0), tmp_path / "free").run()
    counters = result["counters"]
    assert result["learner_updates"] == 40
    assert counters["sampled_sequences"] > 0.5 * counters["added_sequences"]


def test_negative_replay_ratio_is_refused_by_name():
    with pytest.raises(TrainConfigError, match="max_replay_ratio"):
        _short(max_replay_ratio=-1.0)
