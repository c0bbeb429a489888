"""Stage 1 transitions and stage 2 gating / stop rules driven by scripted success streams."""

import pytest

from mapf_fleet.training.curriculum import AlphaCurriculum, ScaleCurriculum


def feed(cur, successes, *args):
    events = []
    for s in successes:
        events.append(cur.record(s, *args))
    return events


def test_scale_needs_a_full_window_above_threshold():
    cur = ScaleCurriculum(1, 10, 3, 20, 5, window=10, threshold=0.9)
    assert not any(feed(cur, [True] * 9))  # window not full yet
    assert cur.setting == (1, 10)
    assert cur.record(True)  # 10/10 > 0.9
    assert cur.setting == (2, 15)
    # exactly 0.9 does not pass (strictly greater, as in the paper)
    assert not any(feed(cur, [False] + [True] * 9))
    assert cur.setting == (2, 15)
    assert cur.record(True)  # last 10: 10 True... window slid past the failure
    assert cur.setting == (3, 20) and cur.done
    assert not cur.record(True)  # nothing after the final setting


def test_scale_caps_map_size_and_keeps_adding_agents():
    cur = ScaleCurriculum(1, 10, 4, 15, 5, window=2, threshold=0.9)
    settings = []
    while not cur.done:
        if cur.record(True):
            settings.append(cur.setting)
    assert settings == [(2, 15), (3, 15), (4, 15)]


def test_scale_state_roundtrip():
    cur = ScaleCurriculum(1, 10, 12, 40, 5, window=5)
    feed(cur, [True] * 5 + [True, False])
    other = ScaleCurriculum(1, 10, 12, 40, 5, window=5)
    other.load_state_dict(cur.state_dict())
    assert other.setting == (2, 15) and list(other.window.flags) == [True, False]


def test_alpha_curriculum_passes_then_stops_on_plateau():
    cur = AlphaCurriculum(window=10, threshold=0.9, max_updates=0, plateau_windows=3,
                          min_delta=0.01)
    assert feed(cur, [True] * 10, 0)[-1] == "passed"
    assert cur.alpha == pytest.approx(0.1) and cur.passed == [0.0]
    assert feed(cur, [True] * 10, 0)[-1] == "passed"
    assert cur.alpha == pytest.approx(0.2)
    # alpha 0.2 stalls at 0.5 success: first window sets the best, then 3 stale windows
    stream = [True, False] * 5
    events = feed(cur, stream * 3, 0)
    assert "failed" not in events and not cur.done
    assert feed(cur, stream, 0)[-1] == "failed"
    assert cur.done and cur.alpha_star == pytest.approx(0.1)
    assert "did not rise" in cur.stop_reason
    assert cur.record(True, 0) is None


def test_alpha_rising_success_is_not_a_plateau():
    cur = AlphaCurriculum(window=10, threshold=0.9, max_updates=0, plateau_windows=2)
    for good in range(1, 9):  # 0.1, 0.2, ... 0.8: always rising
        events = feed(cur, [True] * good + [False] * (10 - good), 0)
        assert "failed" not in events
    assert not cur.done


def test_alpha_update_budget_fails_and_first_alpha_gives_none():
    cur = AlphaCurriculum(window=10, max_updates=100, plateau_windows=0)
    assert cur.record(False, 1000) is None  # budget starts at the first episode (1000)
    assert cur.check_budget(1099) is None
    assert cur.check_budget(1100) == "failed"
    assert cur.done and cur.alpha_star is None


def test_alpha_budget_restarts_per_alpha():
    cur = AlphaCurriculum(window=5, max_updates=100, plateau_windows=0)
    assert feed(cur, [True] * 5, 90)[-1] == "passed"
    assert cur.check_budget(189) is None  # 0.1 started at 90
    assert cur.check_budget(190) == "failed" and cur.alpha_star == 0.0


def test_alpha_gate_window_opens_after_min_updates_at_each_alpha():
    """With alpha_min_updates the episodes of the first N updates at an alpha do not count: a
    policy that has not trained at the new alpha yet cannot pass its gate."""
    cur = AlphaCurriculum(window=5, max_updates=100, plateau_windows=0, min_updates=30)
    assert feed(cur, [True] * 50, 0) == [None] * 50  # updates 0..29 only: window still empty
    assert len(cur.window.flags) == 0
    assert feed(cur, [True] * 5, 29)[-1] is None
    assert feed(cur, [True] * 5, 30)[-1] == "passed" and cur.alpha == pytest.approx(0.1)
    assert feed(cur, [True] * 5, 59)[-1] is None  # 0.1 began at update 30
    assert feed(cur, [True] * 5, 60)[-1] == "passed" and cur.passed == [0.0, 0.1]
    # the budget still runs from the start of the alpha
    assert cur.check_budget(159) is None and cur.check_budget(160) == "failed"
    assert cur.alpha_star == pytest.approx(0.1)


def test_alpha_max_stops_with_last_alpha():
    cur = AlphaCurriculum(alpha_step=0.5, alpha_max=1.0, window=2, max_updates=10)
    for _ in range(3):
        feed(cur, [True, True], 0)
    assert cur.passed == [0.0, 0.5, 1.0] and cur.done and cur.alpha_star == 1.0


def test_fixed_alpha_mode_is_the_ablation():
    cur = AlphaCurriculum(mode="fixed", fixed_alpha=0.3, window=4, max_updates=10)
    assert cur.alpha == 0.3
    assert feed(cur, [True] * 4, 0)[-1] == "passed"
    assert cur.done and cur.alpha_star == 0.3 and cur.passed == [0.3]


def test_alpha_state_roundtrip():
    cur = AlphaCurriculum(window=4, max_updates=50, plateau_windows=2)
    feed(cur, [True] * 4 + [False, True], 7)
    other = AlphaCurriculum(window=4, max_updates=50, plateau_windows=2)
    other.load_state_dict(cur.state_dict())
    assert other.state_dict() == cur.state_dict()
    assert other.check_budget(57) == "failed"


def test_empty_success_windows_are_not_logged_as_zero():
    """A gate window cleared at a new alpha (or setting) has no success rate yet: the TensorBoard
    curve must not drop to 0 there, and the progress bar shows no rate."""
    from types import SimpleNamespace

    from mapf_fleet.training.curriculum import SuccessWindow
    from mapf_fleet.training.trainer import STAGE_ALPHA, Trainer

    class Writer:
        def __init__(self):
            self.scalars = {}

        def add_scalar(self, tag, value, step):
            self.scalars[tag] = value

        def flush(self):
            pass

    class Bar:
        def set_postfix_str(self, text):
            self.text = text

    full, empty = SuccessWindow(4), SuccessWindow(4)
    for flag in (True, True, False, True):
        full.add(flag)
    trainer = SimpleNamespace(
        learner=SimpleNamespace(updates=10), bar=Bar(), bar_actor_rate=None, stage=STAGE_ALPHA,
        cfg=SimpleNamespace(task_mix={}),
        task=SimpleNamespace(num_agents=4, map_size=25, alpha=0.3),
        scale=SimpleNamespace(window=full), alpha=SimpleNamespace(window=empty),
        setting_windows={"4x25": full, "5x30": empty}, replay=[0] * 3)
    rates = {"actor_agent_steps_per_s": 100.0, "learner_updates_per_s": 1.0}
    writer = Writer()
    Trainer._write_scalars(trainer, writer, {"loss": 0.5}, rates)
    assert "curriculum/gate_success_rate" not in writer.scalars  # the alpha stage's window is empty
    assert writer.scalars["success_rate/4x25"] == 0.75 and "success_rate/5x30" not in writer.scalars
    assert "| success – |" in trainer.bar.text
    empty.add(True)
    Trainer._write_scalars(trainer, writer, {}, rates)
    assert writer.scalars["curriculum/gate_success_rate"] == 1.0
    assert "| success 1.00 |" in trainer.bar.text
