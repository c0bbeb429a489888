"""The end of a fleet run, and its progress on the way: what `FleetRun` reports (`RunReport`, a
base class of `run.FleetRun`: the same attributes, read only here). A one-shot run succeeds with
every robot on its goal; a task list when every task is done; a lifelong or external run when it
ran to its end (the tick limit) without being stopped and no accepted task is still queued."""

from __future__ import annotations

import time


def plural(count: int, word: str) -> str:
    """'1 goal', '2 goals', '0 goals'."""
    return f"{count} {word}" + ("" if count == 1 else "s")


class RunReport:
    """`progress`, `progress_text` and `finish` of a `run.FleetRun` (see the module docstring)."""

    def progress(self, missing=()) -> dict:
        """The FleetProgress fields after the last tick."""
        rec = self.recorder
        return dict(episode=rec.episode, tick=self.tick, max_steps=self.max_steps,
                    num_robots=self.num_robots, on_goal=int(self.on_goal().sum()),
                    collisions=rec.collisions, missed_decisions=rec.missed,
                    missed_robots=list(missing), goals_reached=self.goals_reached,
                    busy=self.busy, queued=len(self.queue))

    def progress_text(self) -> str:
        rec = self.recorder
        head = (f"tick {self.tick}: {int(self.on_goal().sum())}/{self.num_robots} on goal"
                if not self.tasks.continuous else
                f"tick {self.tick}: {plural(self.goals_reached, 'goal')} reached "
                f"({self.throughput:.2f}/tick), {self.busy} busy, {len(self.queue)} queued")
        return (f"{head}, {plural(rec.collisions, 'collision')}, "
                f"{plural(rec.missed, 'missed decision')}")

    def finish(self, extra: str = "", stopped_at: int | None = None) -> dict:
        """The FleetOutcome fields (with its summary); `extra` is appended to the summary.
        `stopped_at`: the run was stopped (signal, failure) at that tick: a failure whose
        summary starts with "stopped at tick k". A one-shot run succeeds with every robot on its
        goal; a task list when every task is done; a lifelong or external run when it ran to
        its end (the tick limit) without being stopped."""
        rec = self.recorder
        reason = self.finished()
        if not self.tasks.continuous:
            success = bool(self.on_goal().all()) and stopped_at is None
        elif self.tasks.name == "tasks":
            success = reason == "every task done" and stopped_at is None
        else:  # a task accepted but still queued at the end was not served
            success = stopped_at is None and bool(reason) and not self.queue
        verdict = ('success' if success else 'failure') if stopped_at is None else \
            f"stopped at tick {stopped_at}"
        if self.tasks.continuous:
            done = int(self.tasks_done.sum())
            tasks = (f", {plural(done, 'task')} done" if done or self.tasks.name in ("tasks", "external")
                     else "") + (f", {len(self.queue)} queued" if self.queue else "")
            body = (f"{plural(self.goals_reached, 'goal')} reached in {plural(rec.steps, 'step')} "
                    f"(throughput "
                    f"{self.throughput:.3f} goals/step{tasks}; task source {self.tasks.name}")
            body += f", {reason})" if reason else ")"
        else:
            body = (f"{int(self.on_goal().sum())}/{self.num_robots} robots on goal after "
                    f"{plural(rec.steps, 'step')}")
        summary = (f"{verdict}: {body}, {plural(rec.collisions, 'collision')}, "
                   f"{plural(rec.missed, 'missed decision')}"
                   + (f" (robots {sorted(rec.missed_robots)})" if rec.missed_robots else "")
                   + (f", {plural(rec.overridden, 'overridden move')} ({rec.conflict_rule})"
                      if rec.conflict_rule else "")
                   + extra)
        if stopped_at is not None:
            rec.record["stopped_at_tick"] = int(stopped_at)
        rec.record.pop("incomplete", None)
        rec.record.update(run_seconds=time.monotonic() - rec.started,
                          success=success, steps=rec.steps, collisions=rec.collisions,
                          missed_decisions=rec.missed, summary=summary,
                          goals_reached=self.goals_reached, throughput=self.throughput,
                          tasks_done=self.tasks_done.tolist(),
                          reached_per_robot=self.reached_per_robot.tolist(),
                          final_goals=self.goals.tolist())
        if rec.conflict_rule:
            rec.record["overridden_moves"] = rec.overridden
        planner = getattr(self.arbiter.shield, "stats", None)
        if planner is not None:  # the planning arbiter's counters (calls, time, fallbacks)
            stats = planner()
            rec.record["planner"] = stats
            summary += (f"; planner: {stats['planner_calls']} calls, "
                        f"{stats['planner_seconds_per_call'] * 1000:.0f} ms per call (max "
                        f"{stats['planner_max_seconds'] * 1000:.0f}), fallback ticks "
                        f"{stats['fallback_ticks']}/{stats['ticks']}")
            rec.record["summary"] = summary
        return dict(episode=rec.episode, success=success, steps=rec.steps,
                    num_robots=self.num_robots, collisions=rec.collisions,
                    missed_decisions=rec.missed, missed_robots=sorted(rec.missed_robots),
                    summary=summary, goals_reached=self.goals_reached,
                    throughput=float(self.throughput), tasks_done=self.tasks_done.tolist(),
                    task_source=self.tasks.name)
