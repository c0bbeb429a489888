"""`mapf-fleet dagger` and `mapf-fleet train` under a burst of SIGINT / SIGTERM (Ctrl-C held
down): the run stops at its next check with its state saved, "stopped by SIGINT", and the
process ends; the handlers (mapf_fleet/stop_signals.py) only set a flag, so no burst can hang
it. Tiny runs in a subprocess, signals from this process."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

DAGGER = """
import sys, torch
sys.path.insert(0, {test_dir!r})
from mapf_fleet.models.checkpoint import build_model, save_checkpoint
from mapf_fleet.models.config import ModelConfig
from mapf_fleet.training import dagger
from test_training_dagger import tiny_config
torch.manual_seed(0)
save_checkpoint({ckpt!r}, build_model(ModelConfig.preset("dcc", "small")),
                {{"alpha": 0.0, "curriculum": {{}}, "learner_steps": 0, "training_config": {{}}}})
cfg = tiny_config({ckpt!r}, rounds=200)
result = dagger.Dagger(cfg, {run!r}, log=lambda m: print("log", m, flush=True)).run()
print("result", result["stop"], flush=True)
"""


def _burst(pid: int, count: int = 300) -> None:
    for k in range(count):
        try:
            os.kill(pid, (signal.SIGINT, signal.SIGTERM)[k % 3 == 2])
        except ProcessLookupError:
            return


@pytest.mark.slow
def test_dagger_stops_on_a_burst_of_signals(tmp_path):
    code = DAGGER.format(test_dir=str(REPO / "test"), ckpt=str(tmp_path / "small.pt"),
                         run=str(tmp_path / "run"))
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=str(REPO))
    try:
        for line in proc.stdout:  # the rounds have begun (the baselines are logged)
            if line.startswith("log held-out"):
                break
        time.sleep(0.5)
        _burst(proc.pid)
        sent = time.monotonic()
        out, err = proc.communicate(timeout=120)
        stopped_in = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err[-3000:]
    assert "result stopped by SIGINT" in out, out[-3000:]
    assert "Traceback" not in err, err[-3000:]
    assert stopped_in < 60
    assert (tmp_path / "run" / "state.json").is_file()


@pytest.mark.slow
def test_train_stops_on_a_burst_of_signals_with_its_state_saved(tmp_path):
    """The trainer's old handler logged (a lock in the progress bar) and raised
    KeyboardInterrupt on the second signal: a burst aborted the run without saving it."""
    import json

    from mapf_fleet.training import run_state

    run = tmp_path / "run"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    sets = ["use_ray=false", "num_actors=1", "envs_per_actor=4", "actor_steps_per_call=8",
            "learning_starts=50", "state_interval_updates=5", "batch_size=4",
            "max_updates=100000", "alpha_max_updates=100000", "demo_source=none"]
    cmd = [sys.executable, "-m", "mapf_fleet.cli", "train", "--config",
           str(REPO / "config" / "training" / "tiny.yaml"), "--run-dir", str(run)]
    for item in sets:
        cmd += ["--set", item]
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            time.sleep(0.5)
            assert proc.poll() is None, proc.stderr.read()[-2000:]
            if (run / run_state.STATE_FILE).exists() and \
                    run_state.load_state(run)["learner"]["updates"] >= 5:
                break
        _burst(proc.pid)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    result = json.loads((run / run_state.RESULT_FILE).read_text())
    assert "SIGINT" in result["stop_reason"] and not result["finished"]
    assert run_state.load_state(run)["learner"]["updates"] == result["learner_updates"]
