"""What a checkpoint cost: wall time x the CPUs the run reserved, and the CPU time the trainer
measured (`compute_spent`), from the checkpoint's own counters or its run directory."""

from __future__ import annotations

from dataclasses import dataclass

from .inputs import RunInfo


@dataclass(frozen=True)
class Compute:
    wall_seconds: float
    cpus: int | None
    source: str  # which file the wall time came from
    how: str  # the CPU count's origin
    measured_cpu_seconds: float | None = None  # counters.cpu_seconds: process CPU time measured
    measured_from_elapsed: float = 0.0  # the run's wall time before the trainer measured it

    @property
    def cpu_hours(self) -> float | None:
        return None if self.cpus is None else self.wall_seconds * self.cpus / 3600.0


def compute_spent(run: RunInfo | None, metadata: dict) -> Compute | None:
    """Wall time (summed over resumed sessions by the trainer's counters.elapsed_seconds) x the
    CPUs the run reserved, and the measured CPU time. A checkpoint holding the run's counters of
    its own moment (`extra.counters`, written by the trainer since they were added) is measured
    up to itself; otherwise the whole run: the latest of result.json and train_state.pt wins, and
    a checkpoint's `extra.elapsed_seconds` is used without a run dir."""
    extra = metadata.get("extra") or {}
    own = extra.get("counters")
    if isinstance(own, dict) and _is_number(own.get("elapsed_seconds")):
        # checkpoints the trainer writes now carry the run's counters of that moment
        return _compute_from(own, CHECKPOINT_POINT, run, metadata)
    candidates = []
    if run is not None:
        if run.result and isinstance(run.result.get("counters"), dict):
            candidates.append((run.result["counters"], "result.json counters.elapsed_seconds"))
        if run.state_counters:
            candidates.append((run.state_counters, "train_state.pt counters.elapsed_seconds"))
    candidates.append((extra, "checkpoint metadata extra.elapsed_seconds"))
    candidates = [(c, s) for c, s in candidates if _is_number(c.get("elapsed_seconds"))]
    if not candidates:
        return None
    counters, source = max(candidates, key=lambda c: float(c[0]["elapsed_seconds"]))
    return _compute_from(counters, source, run, metadata)


CHECKPOINT_POINT = "checkpoint metadata extra.counters, i.e. the run when this checkpoint was written"


def _compute_from(counters: dict, source: str, run: RunInfo | None, metadata: dict) -> Compute:
    wall = float(counters["elapsed_seconds"])
    measured = (float(counters["cpu_seconds"]) if _is_number(counters.get("cpu_seconds")) else None,
                float(counters.get("cpu_measured_from_elapsed_seconds") or 0.0))
    uncounted = uncounted_warm_start_seconds(run)
    if uncounted:
        wall += uncounted
        if measured[0] is not None:  # that warm start came before the CPU measurement began
            measured = (measured[0], measured[1] + uncounted)
        source += (f" + {uncounted:.0f} s of demonstration warm start that the trainer did not yet "
                   "count (runs started before it did: from the tb event file's creation to the "
                   "last demo/loss scalar)")
    config = (run.config if run and run.config else None) or metadata.get("training_config") or {}
    if config.get("ray_address"):
        cpus, how = None, "an external Ray cluster (ray_address): CPUs unknown"
    elif config.get("use_ray", True) and isinstance(config.get("num_cpus"), int):
        cpus, how = config["num_cpus"], "`num_cpus` of the local Ray (training config)"
    elif config.get("use_ray") is False and isinstance(config.get("learner_threads"), int):
        cpus, how = config["learner_threads"], "in-process actors (use_ray false): the learner's `learner_threads`"
    else:
        cpus, how = None, "the training config names no CPU count"
    return Compute(wall, cpus, source, how, *measured)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def uncounted_warm_start_seconds(run: RunInfo | None) -> float:
    """Runs begun before the trainer counted its demonstration warm start in elapsed_seconds
    but which logged demo/ scalars: the warm start's wall time, from the first event of the event
    file holding demo/loss to its last demo/loss scalar of the warm start (step <=
    demo_pretrain_updates; later ones are interleaved demo updates). Counted already when the
    run's `demo_seconds` (all warm starts and demonstration refreshes the trainer timed) holds at
    least 90 % of it; a run that began uncounted and got `demo_seconds` in a later session only
    holds its refreshes there."""
    if run is None or run.tb_dir is None:
        return 0.0
    counters = run.state_counters or (run.result or {}).get("counters") or {}
    if not counters.get("demo_pretrained"):
        return 0.0
    counted = float(counters.get("demo_seconds") or 0.0)
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    for path in sorted(run.tb_dir.glob("events.out.tfevents.*")):
        accumulator = EventAccumulator(str(path), size_guidance={"scalars": 0})
        accumulator.Reload()
        if "demo/loss" in accumulator.Tags().get("scalars", []):
            limit = int((run.config or {}).get("demo_pretrain_updates") or 0)
            warm = [e for e in accumulator.Scalars("demo/loss") if not limit or e.step <= limit]
            if warm:
                seconds = float(warm[-1].wall_time - accumulator.FirstEventTimestamp())
                return 0.0 if counted >= 0.9 * seconds else seconds
    return 0.0
