"""The two curricula of the paper (Algorithm 1), driven by a stream of episode outcomes.

Stage 1 `ScaleCurriculum`: start small; whenever the success rate over the last `window`
episodes exceeds `threshold`, add one agent and grow the map by `map_step` (capped at the final
size); the stage is over once the final setting is reached (Algorithm 1, line 3). With
`single_gate` (the trainer's choice under a training mix, `TrainConfig.task_mix`, where the mix
and not a ladder defines the tasks) one pass of the same gate jumps to the final setting, so the
stage is one gate at alpha 0 on the mix's tasks.

Stage 2 `AlphaCurriculum`: at the final setting, alpha from 0 up by `alpha_step`. Passing the gate
(same rule) records alpha as passed and raises it. An alpha *fails* ("converged without reaching
the threshold", Algorithm 1 line 19) when either rule fires first:
  - budget: `max_updates` learner updates spent at this alpha without passing, or
  - plateau: `plateau_windows` consecutive full, non-overlapping windows of `window` episodes
    (counted from the start of this alpha) none of which beat the best rate so far at this alpha
    by more than `min_delta`.
On failure the curriculum stops with alpha* = the last passed alpha (None when none passed).
Passing alpha_max stops with alpha* = alpha_max. Mode "fixed" is the paper's "w/o CL" ablation:
one alpha (`fixed_alpha`) right after stage 1, same gate and stop rules. Mode "none" skips stage 2.
"""

from __future__ import annotations

from collections import deque


class SuccessWindow:
    """Success flags of the most recent `size` episodes."""

    def __init__(self, size: int):
        self.size = size
        self.flags: deque[bool] = deque(maxlen=size)

    def add(self, success: bool) -> None:
        self.flags.append(bool(success))

    @property
    def full(self) -> bool:
        return len(self.flags) == self.size

    @property
    def rate(self) -> float:
        return sum(self.flags) / len(self.flags) if self.flags else 0.0

    def clear(self) -> None:
        self.flags.clear()

    def state_dict(self) -> dict:
        return {"flags": [bool(f) for f in self.flags]}

    def load_state_dict(self, state: dict) -> None:
        self.flags = deque((bool(f) for f in state["flags"]), maxlen=self.size)


class ScaleCurriculum:
    def __init__(self, start_agents: int = 1, start_map_size: int = 10, final_agents: int = 12,
                 final_map_size: int = 40, map_step: int = 5, window: int = 200,
                 threshold: float = 0.9, single_gate: bool = False):
        self.final_agents, self.final_map_size = final_agents, final_map_size
        self.map_step, self.threshold = map_step, threshold
        self.single_gate = single_gate
        self.num_agents, self.map_size = start_agents, min(start_map_size, final_map_size)
        self.window = SuccessWindow(window)
        self.transitions = 0

    @property
    def setting(self) -> tuple[int, int]:
        return self.num_agents, self.map_size

    @property
    def done(self) -> bool:
        return self.num_agents >= self.final_agents and self.map_size >= self.final_map_size

    def record(self, success: bool) -> bool:
        """Add one episode outcome at the current setting; True when the setting advanced."""
        if self.done:
            return False
        self.window.add(success)
        if self.window.full and self.window.rate > self.threshold:
            if self.single_gate:
                self.num_agents, self.map_size = self.final_agents, self.final_map_size
            else:
                self.num_agents = min(self.num_agents + 1, self.final_agents)
                self.map_size = min(self.map_size + self.map_step, self.final_map_size)
            self.window.clear()
            self.transitions += 1
            return True
        return False

    def state_dict(self) -> dict:
        return {"num_agents": self.num_agents, "map_size": self.map_size,
                "transitions": self.transitions, "window": self.window.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.num_agents, self.map_size = int(state["num_agents"]), int(state["map_size"])
        self.transitions = int(state["transitions"])
        self.window.load_state_dict(state["window"])


class AlphaCurriculum:
    PASSED, FAILED = "passed", "failed"

    def __init__(self, mode: str = "curriculum", alpha_step: float = 0.1, alpha_max: float = 1.0,
                 fixed_alpha: float = 0.3, window: int = 200, threshold: float = 0.9,
                 max_updates: int = 100_000, plateau_windows: int = 10,
                 min_delta: float = 0.01, min_updates: int = 0):
        if mode not in ("curriculum", "fixed", "none"):
            raise ValueError(f"AlphaCurriculum mode must be curriculum|fixed|none, got {mode!r}")
        self.mode, self.alpha_step, self.alpha_max = mode, alpha_step, alpha_max
        self.threshold, self.max_updates, self.min_updates = threshold, max_updates, min_updates
        self.plateau_windows, self.min_delta = plateau_windows, min_delta
        self.window = SuccessWindow(window)
        self.alpha = fixed_alpha if mode == "fixed" else 0.0
        self.passed: list[float] = []
        self.done = mode == "none"
        self.alpha_star: float | None = None
        self.stop_reason = "stage 2 disabled" if self.done else ""
        self.start_updates: int | None = None  # learner updates when this alpha began
        self.episodes_at_alpha = 0
        self.best_rate = -1.0
        self.stale_windows = 0

    def begin(self, updates: int) -> None:
        """Start counting the budget of the current alpha (call when stage 2 starts)."""
        if self.start_updates is None:
            self.start_updates = updates

    def _next_alpha(self, updates: int) -> None:
        self.window.clear()
        self.start_updates = updates
        self.episodes_at_alpha = 0
        self.best_rate = -1.0
        self.stale_windows = 0

    def _fail(self, reason: str) -> str:
        self.done = True
        self.alpha_star = self.passed[-1] if self.passed else None
        self.stop_reason = reason
        return self.FAILED

    def record(self, success: bool, updates: int) -> str | None:
        """Add one episode outcome at the current alpha; returns "passed", "failed" or None."""
        if self.done:
            return None
        self.begin(updates)
        if updates - self.start_updates < self.min_updates:
            return None  # still training at this alpha: its gate window has not opened yet
        self.window.add(success)
        self.episodes_at_alpha += 1
        if self.window.full and self.window.rate > self.threshold:
            self.passed.append(self.alpha)
            if self.mode == "fixed":
                self.done, self.alpha_star = True, self.alpha
                self.stop_reason = f"fixed alpha {self.alpha:g} passed the gate"
            else:
                nxt = round(self.alpha + self.alpha_step, 10)
                if nxt > self.alpha_max + 1e-9:
                    self.done, self.alpha_star = True, self.alpha
                    self.stop_reason = f"alpha reached alpha_max {self.alpha_max:g}"
                else:
                    self.alpha = nxt
            self._next_alpha(updates)
            return self.PASSED
        if self.plateau_windows and self.episodes_at_alpha % self.window.size == 0:
            rate = self.window.rate
            if rate > self.best_rate + self.min_delta:
                self.best_rate, self.stale_windows = rate, 0
            else:
                self.stale_windows += 1
                if self.stale_windows >= self.plateau_windows:
                    return self._fail(f"alpha {self.alpha:g}: success rate did not rise above "
                                      f"{self.best_rate:.3f} for {self.stale_windows} windows")
        return self.check_budget(updates)

    def check_budget(self, updates: int) -> str | None:
        """Fail the current alpha when its learner-update budget is spent."""
        if self.done or not self.max_updates or self.start_updates is None:
            return None
        if updates - self.start_updates >= self.max_updates:
            return self._fail(f"alpha {self.alpha:g}: {self.max_updates} learner updates "
                              f"without passing the gate")
        return None

    def state_dict(self) -> dict:
        return {"alpha": self.alpha, "passed": list(self.passed), "done": self.done,
                "alpha_star": self.alpha_star, "stop_reason": self.stop_reason,
                "start_updates": self.start_updates, "episodes_at_alpha": self.episodes_at_alpha,
                "best_rate": self.best_rate, "stale_windows": self.stale_windows,
                "window": self.window.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.alpha = float(state["alpha"])
        self.passed = [float(a) for a in state["passed"]]
        self.done = bool(state["done"])
        self.alpha_star = None if state["alpha_star"] is None else float(state["alpha_star"])
        self.stop_reason = str(state["stop_reason"])
        self.start_updates = None if state["start_updates"] is None else int(state["start_updates"])
        self.episodes_at_alpha = int(state["episodes_at_alpha"])
        self.best_rate = float(state["best_rate"])
        self.stale_windows = int(state["stale_windows"])
        self.window.load_state_dict(state["window"])
