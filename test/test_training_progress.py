"""The training progress bar's actor rate: actor results come in bursts (one per actor call, and a
call can outlast the log interval); the bar and the `rate/actor_agent_steps_per_s` scalar must
not read 0 agent-steps/s between bursts, nor a burst's steps over one short window."""

import re
import time
from pathlib import Path

from mapf_fleet.training import trainer as trainer_module
from mapf_fleet.training.config import load_config

CONFIGS = Path(__file__).resolve().parents[1] / "config" / "training"
CALL_SECONDS = 0.4  # one actor call; the log interval below is 8x shorter


class BurstyActors(trainer_module._LocalActors):
    """In-process actors whose results arrive at most every CALL_SECONDS, like a Ray actor whose
    remote call takes longer than the trainer's log interval."""

    def __init__(self, cfg):
        super().__init__(cfg)
        self.ready_at = time.monotonic() + CALL_SECONDS

    def poll(self, task, block):
        wait = self.ready_at - time.monotonic()
        if wait > 0:
            if not block:
                return []
            time.sleep(wait)
        results = super().poll(task, block)
        self.ready_at = time.monotonic() + CALL_SECONDS
        return results


def test_actor_rate_is_never_zero_between_bursts(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(trainer_module, "_LocalActors", BurstyActors)
    logged = []
    real = trainer_module.Trainer._write_scalars

    def spy(self, writer, stats, rates):
        logged.append(dict(rates))
        return real(self, writer, stats, rates)

    monkeypatch.setattr(trainer_module.Trainer, "_write_scalars", spy)
    cfg = load_config(CONFIGS / "tiny.yaml").replace(
        use_ray=False, num_actors=1, envs_per_actor=2, actor_steps_per_call=64, batch_size=4,
        seq_len=4, burn_in=0, learning_starts=8, demo_source="none", max_updates=100_000,
        max_wall_seconds=3.0, log_interval_seconds=CALL_SECONDS / 8, progress_bar=True)
    began = time.monotonic()
    result = trainer_module.Trainer(cfg, tmp_path / "run").run()
    wall = time.monotonic() - began
    steps = result["counters"]["agent_steps"]
    assert steps > 0 and len(logged) >= 10

    shown = [float(v) for v in re.findall(r"([0-9.]+) agent-steps/s", capsys.readouterr().err)]
    assert shown and 0.0 not in shown, shown
    rates = [r["actor_agent_steps_per_s"] for r in logged if "actor_agent_steps_per_s" in r]
    assert rates and 0.0 not in rates, rates
    # each measured rate is the steps since the previous burst over the time since it: close to
    # the run's average, not a burst over one log interval (which read ~8x the average)
    average = steps / wall
    assert all(average / 3 < r < 3 * average for r in rates[1:]), (average, rates)
