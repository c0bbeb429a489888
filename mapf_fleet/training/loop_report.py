"""What the training loop reports: its pace (`Pace`: clocks, rates, when the next log and saves
are due) and its scalars (`write_scalars`: the progress bar and TensorBoard)."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .ray_pool import CpuMeter

STAGE_SCALE, STAGE_ALPHA, STAGE_DONE = "scale", "alpha", "done"


class Pace:
    """The loop's clocks and rates: elapsed and CPU time into the counters, and when the next
    log, state save and replay save are due. Actor results arrive in bursts (one per actor call,
    which may outlast a log interval): the actor rate spans from the last log that had results."""

    def __init__(self, counters: dict, cpu: CpuMeter, cpu0: float, updates: int):
        self.counters, self.cpu, self.cpu0 = counters, cpu, cpu0
        self.start = self.last_log = self.last_state_time = self.last_replay = time.monotonic()
        self.elapsed0 = counters["elapsed_seconds"]
        self.last_state = updates
        self.steps, self.updates, self.rate_t, self.steps_t = 0, 0, self.start, self.start

    def wall(self) -> float:
        return time.monotonic() - self.start

    def tick(self) -> float:
        now = time.monotonic()
        self.counters["elapsed_seconds"] = self.elapsed0 + now - self.start
        self.counters["cpu_seconds"] = self.cpu0 + self.cpu.seconds()
        return now

    def rates(self, now: float) -> dict:
        """The rates since the last log, and start the next span."""
        rates = {"learner_updates_per_s": self.updates / max(now - self.rate_t, 1e-9)}
        if self.counters["added_sequences"]:
            rates["replay_ratio"] = (self.counters["sampled_sequences"]
                                     / self.counters["added_sequences"])
        if self.steps:  # no result since the last log: no new actor rate, not 0
            rates["actor_agent_steps_per_s"] = self.steps / max(now - self.steps_t, 1e-9)
            self.steps, self.steps_t = 0, now
        self.updates, self.rate_t, self.last_log = 0, now, now
        return rates


def write_scalars(self, writer, stats: dict, rates: dict) -> None:
    """The trainer's progress bar and TensorBoard scalars after a bookkeeping turn (`self`: the
    `Trainer`; the tags are what model cards read, evaluation/model_card/curves.py)."""
    step = self.learner.updates
    gate = self.scale.window if self.stage == STAGE_SCALE else self.alpha.window
    if self.bar is not None:
        agents, size = self.task.num_agents, self.task.map_size
        tasks = "task mix" if self.cfg.task_mix else f"{agents} agents {size}x{size}"
        success = f"{gate.rate:.2f}" if gate.flags else "–"
        self.bar_actor_rate = rates.get("actor_agent_steps_per_s", self.bar_actor_rate)
        steps = "–" if self.bar_actor_rate is None else f"{self.bar_actor_rate:.0f}"
        self.bar.set_postfix_str(
            f"stage {self.stage} | {tasks} | alpha {self.task.alpha:.1f}"
            f" | success {success} | {steps} agent-steps/s"
            f" | {rates['learner_updates_per_s']:.2f} upd/s")
    if writer is None:
        return
    for key in ("loss", "mean_q", "mean_abs_td", "grad_norm"):
        if key in stats:
            writer.add_scalar(f"learner/{key}", stats[key], step)
    for key, value in rates.items():
        writer.add_scalar(f"rate/{key}", value, step)
    writer.add_scalar("curriculum/stage", {STAGE_SCALE: 1, STAGE_ALPHA: 2}.get(self.stage, 3),
                      step)
    if not self.cfg.task_mix:  # under a mix the setting chooses no task
        writer.add_scalar("curriculum/num_agents", self.task.num_agents, step)
        writer.add_scalar("curriculum/map_size", self.task.map_size, step)
    writer.add_scalar("curriculum/alpha", self.task.alpha, step)
    # An empty window (just cleared at a new setting or alpha, or waiting out alpha_min_updates)
    # has no rate: logging 0 would draw a collapse of success that did not happen.
    if gate.flags:
        writer.add_scalar("curriculum/gate_success_rate", gate.rate, step)
    for key, window in self.setting_windows.items():
        if window.flags:
            writer.add_scalar(f"success_rate/{key}", window.rate, step)
    writer.add_scalar("replay/sequences", len(self.replay), step)
    writer.flush()


def warm_start_bar(self, stats: dict) -> None:
    """The bar during the demo warm start (its updates count towards max_updates)."""
    if self.bar is not None:
        self.bar.update(1)
        if self.learner.updates % 10 == 0:
            self.bar.set_postfix_str(f"demo warm start | agreement "
                                     f"{stats.get('demo_agreement', 0.0):.2f}")
