"""Run directory, config loading and resume after kill -9."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from mapf_fleet.training import run_state
from mapf_fleet.training.config import TrainConfig, TrainConfigError, config_from_dict, load_config
from mapf_fleet.training.trainer import Trainer

REPO = Path(__file__).resolve().parent.parent
CONFIGS = REPO / "config" / "training"


TRAIN_CONFIGS = sorted(p for p in [*CONFIGS.glob("*.yaml"), *CONFIGS.glob("experiments/*.yaml")]
                       if not p.name.startswith("dagger_"))  # dagger_*: DAgger's (own test)


def test_the_configs_to_train_with_are_there():
    names = {p.stem for p in TRAIN_CONFIGS if p.parent == CONFIGS}
    assert names == {"dhc_paper", "dcc_paper", "dhc_cpu", "dcc_cpu", "dhc_cpu_lacam",
                     "dcc_cpu_lacam", "tiny"}


@pytest.mark.parametrize("path", TRAIN_CONFIGS, ids=lambda p: str(p.relative_to(CONFIGS)))
def test_shipped_configs_load(path):
    cfg = load_config(path)
    assert cfg.algo in ("dhc", "dcc")


def test_paper_defaults_and_dcc_preset():
    dhc = TrainConfig()
    assert (dhc.batch_size, dhc.seq_len, dhc.lr, dhc.target_update_interval) == (192, 16, 1e-4, 2000)
    assert (dhc.gamma, dhc.n_step, dhc.grad_clip, dhc.learning_starts) == (0.99, 2, 40.0, 50_000)
    dcc = config_from_dict({"preset": "dcc"})
    assert (dcc.batch_size, dcc.seq_len, dcc.lr, dcc.final_agents) == (128, 20, 2e-4, 16)


def test_bad_config_names_file_field_and_value(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("batch_size: 0\n")
    with pytest.raises(TrainConfigError, match=r"bad.yaml.*batch_size.*0"):
        load_config(path)
    path.write_text("batchsize: 3\n")
    with pytest.raises(TrainConfigError, match="unknown field 'batchsize'"):
        load_config(path)
    path.write_text("lr: fast\n")
    with pytest.raises(TrainConfigError, match="'lr'.*fast"):
        load_config(path)
    with pytest.raises(TrainConfigError, match="plateau_windows"):
        TrainConfig(alpha_max_updates=0, plateau_windows=0)
    with pytest.raises(TrainConfigError, match=r"'alpha_min_updates' = 500.*alpha_max_updates \(400\)"):
        TrainConfig(alpha_max_updates=400, alpha_min_updates=500)
    # replace() checks like a file does: a string learning rate is read as a number or refused
    assert TrainConfig().replace(lr="2e-3").lr == 2e-3
    with pytest.raises(TrainConfigError, match=r"replace.*'lr'.*fast"):
        TrainConfig().replace(lr="fast")
    with pytest.raises(TrainConfigError, match=r"'batch_size'.*2.5.*integer"):
        TrainConfig().replace(batch_size=2.5)


def _tiny_overrides():
    return ["--set", "use_ray=false", "--set", "num_actors=1", "--set", "envs_per_actor=4",
            "--set", "actor_steps_per_call=8", "--set", "learning_starts=50",
            "--set", "state_interval_updates=5", "--set", "batch_size=4",
            "--set", "max_updates=100000", "--set", "alpha_max_updates=100000",
            "--set", "demo_source=none"]


def test_resume_after_kill_9(tmp_path):
    run = tmp_path / "run"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    cmd = [sys.executable, "-m", "mapf_fleet.cli", "train", "--config",
           str(CONFIGS / "tiny.yaml"), "--run-dir", str(run), *_tiny_overrides()]
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, start_new_session=True)
    try:
        deadline = time.monotonic() + 240
        saved = None
        while time.monotonic() < deadline:
            time.sleep(1.0)
            if proc.poll() is not None:
                pytest.fail(f"trainer exited early: {proc.stderr.read().decode()[-2000:]}")
            if (run / run_state.STATE_FILE).exists():
                saved = run_state.load_state(run)
                if saved["learner"]["updates"] >= 10:
                    break
        assert saved is not None and saved["learner"]["updates"] >= 10, "no state written"
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    saved = run_state.load_state(run)  # the last complete file (writes are atomic)
    trainer = Trainer(load_config(run / run_state.CONFIG_FILE), run, resume=True)
    assert trainer.learner.updates == saved["learner"]["updates"]
    assert trainer.scale.state_dict() == saved["scale"]
    assert trainer.alpha.state_dict() == saved["alpha"]
    assert trainer.counters["episodes"] == saved["counters"]["episodes"]
    opt = trainer.learner.optimizer.state_dict()
    steps = {int(s["step"]) for s in opt["state"].values()}
    assert steps == {saved["learner"]["updates"]}  # Adam moments restored, not restarted
    for name, value in saved["learner"]["model"].items():
        assert torch.equal(trainer.learner.model.state_dict()[name], value)
    # and it continues from there
    trainer.cfg = trainer.cfg.replace(max_updates=trainer.learner.updates + 3, use_ray=False)
    result = trainer.run()
    assert result["learner_updates"] == saved["learner"]["updates"] + 3
    assert (run / "checkpoints" / "final.pt").exists()
    # `mapf-fleet train --export RUN --out F`: the last saved state as a checkpoint file
    from mapf_fleet.models.checkpoint import load_checkpoint
    from mapf_fleet.training.export import export_checkpoint

    path, _ = export_checkpoint(run, tmp_path / "exported.pt")
    model, meta = load_checkpoint(path)
    assert meta["learner_steps"] == result["learner_updates"]
    # two training sessions (killed, resumed), each with the code it ran
    sessions = meta["extra"]["trained_with_code"]
    assert [s["from_update"] for s in sessions] == [0, saved["learner"]["updates"]]
    for name, value in model.state_dict().items():
        assert torch.equal(trainer.learner.model.state_dict()[name], value)
    with pytest.raises(FileNotFoundError, match="not_a_run.*a run directory"):
        export_checkpoint(tmp_path / "not_a_run", tmp_path / "x.pt")
    # `--resume RUN --set F=V`: config.yaml keeps the starting config, the session records it
    from mapf_fleet.training.trainer import train

    before = (run / run_state.CONFIG_FILE).read_text()
    train(resume=run, overrides={"max_updates": result["learner_updates"]})
    last = run_state.load_state(run)["code_versions"][-1]
    assert last["overrides"] == {"max_updates": result["learner_updates"]}
    assert (run / run_state.CONFIG_FILE).read_text() == before
    # ... and a later resume without --set goes on with it (and so does an export)
    from mapf_fleet.training.trainer import resumed_config

    assert load_config(run / run_state.CONFIG_FILE).max_updates != result["learner_updates"]
    assert resumed_config(run).max_updates == result["learner_updates"]
    _, exported = export_checkpoint(run, tmp_path / "exported2.pt")
    assert exported["training_config"]["max_updates"] == result["learner_updates"]


def test_ctrl_c_stops_a_ray_run_and_saves_its_state(tmp_path):
    """SIGINT to `mapf-fleet train` (Ray actors running) ends the run cleanly: exit code 0, the
    state and final checkpoint saved at the update where it stopped, the reason in result.json."""
    run = tmp_path / "run"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    cmd = [sys.executable, "-m", "mapf_fleet.cli", "train", "--config",
           str(CONFIGS / "tiny.yaml"), "--run-dir", str(run), *_tiny_overrides(),
           "--set", "use_ray=true"]
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True)
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            time.sleep(1.0)
            if proc.poll() is not None:
                pytest.fail(f"trainer exited early: {proc.stderr.read().decode()[-2000:]}")
            if (run / run_state.STATE_FILE).exists() and \
                    run_state.load_state(run)["learner"]["updates"] >= 5:
                break
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, err.decode()[-2000:]
    result = json.loads((run / run_state.RESULT_FILE).read_text())
    assert "SIGINT" in result["stop_reason"] and not result["finished"]
    assert run_state.load_state(run)["learner"]["updates"] == result["learner_updates"]
    assert (run / "checkpoints" / "final.pt").exists()
    # the replay was saved too: a resume learns on it instead of a near-empty replay
    assert (run / run_state.REPLAY_FILE).is_file()
    resumed = Trainer(load_config(run / run_state.CONFIG_FILE), run, resume=True)
    assert len(resumed.replay) > 0 and any("replay restored" in e for e in resumed.events)
    # a damaged replay file: the run resumes with an empty replay, says why, keeps the file
    (run / run_state.REPLAY_FILE).write_bytes(b"damaged")
    damaged = Trainer(load_config(run / run_state.CONFIG_FILE), run, resume=True)
    assert len(damaged.replay) == 0
    assert any("replay not restored" in e and "replay.npz" in e for e in damaged.events)
    assert (run / run_state.REPLAY_FILE).read_bytes() == b"damaged"


def test_resume_in_stage_1_takes_stage_2_settings_from_the_config(tmp_path):
    """Stage 2 holds no progress before it begins, so a resume that changes its settings (here
    the final task and `alpha_mode=fixed`, the paper's "w/o CL") trains with them; once stage 2
    has begun its progress is restored instead."""
    cfg = load_config(CONFIGS / "tiny.yaml").replace(use_ray=False, progress_bar=False)
    run = tmp_path / "run"
    trainer = Trainer(cfg, run)
    trainer.scale.num_agents, trainer.scale.map_size = 2, 15
    trainer.save_state()
    fixed = cfg.replace(final_agents=2, final_map_size=15, alpha_mode="fixed", fixed_alpha=0.3)
    resumed = Trainer(fixed, run, resume=True)
    assert resumed.stage == "alpha" and resumed.task.alpha == pytest.approx(0.3)
    assert (resumed.task.num_agents, resumed.task.map_size) == (2, 15)
    resumed.alpha.passed.append(0.3)
    resumed.save_state()
    again = Trainer(fixed, run, resume=True)
    assert again.alpha.passed == [0.3] and again.alpha.alpha == pytest.approx(0.3)


def test_resume_with_another_stage_2_scheme_restarts_stage_2(tmp_path):
    """A fixed-alpha run that is done (its alpha passed the gate, its budget mostly spent)
    forked with `--set alpha_mode=curriculum`: the curriculum starts at alpha 0 with an empty
    gate window and a fresh budget, on the fixed run's weights."""
    cfg = load_config(CONFIGS / "tiny.yaml").replace(
        use_ray=False, progress_bar=False, start_agents=2, start_map_size=15, final_agents=2,
        final_map_size=15,
        alpha_mode="fixed", fixed_alpha=0.0, alpha_max_updates=50)
    run = tmp_path / "run"
    fixed = Trainer(cfg, run)
    assert fixed.stage == "alpha"
    fixed.learner.updates = 40
    for _ in range(cfg.success_window):
        fixed._record_episode({"num_agents": 2, "map_size": 15, "alpha": 0.0, "success": True,
                               "gate": True, "task_version": fixed.task_version})
    assert fixed.stage == "done" and fixed.alpha.alpha_star == 0.0
    fixed.save_state()
    weights = {k: v.clone() for k, v in fixed.learner.model.state_dict().items()}
    forked = Trainer(cfg.replace(alpha_mode="curriculum"), run, resume=True)
    assert forked.stage == "alpha" and forked.alpha.alpha == 0.0
    assert forked.alpha.passed == [] and forked.alpha.alpha_star is None
    assert len(forked.alpha.window.flags) == 0 and forked.alpha.start_updates == 40
    assert any("stage 2 restarted" in e and "fixed alpha 0.0" in e for e in forked.events)
    assert all(torch.equal(weights[k], v) for k, v in forked.learner.model.state_dict().items())
    # the budget counts from the fork: 49 more updates are within alpha_max_updates=50
    assert forked.alpha.check_budget(89) is None


@pytest.mark.parametrize("rule, rankings", [("revert", None),
                                              ("pibt_anchor", {"pibt_anchor": "q_then_distance"})])
def test_checkpoints_of_a_shielded_run_record_their_ranking(tmp_path, rule, rankings):
    """A run trained behind the shield records {rule: ranking} as DAgger's checkpoints do (the
    evaluator and the policy nodes rank with it under that rule unless told otherwise); an
    unshielded run records none."""
    from mapf_fleet.models.checkpoint import load_checkpoint

    cfg = load_config(CONFIGS / "tiny.yaml").replace(
        use_ray=False, demo_source="none", conflict_rule=rule, ranking="q_then_distance")
    trainer = Trainer(cfg, tmp_path / "run")
    _, meta = load_checkpoint(trainer.save_checkpoint("x.pt"))
    assert meta.get("rankings") == rankings
