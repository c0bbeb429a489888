"""The training loop: Ape-X actors (Ray or in-process), replay, learner, both curricula,
run directory, TensorBoard, progress bar, resume.

The driver process holds the replay and the learner; actors are Ray actors that each play
`actor_steps_per_call` batched steps per call with the latest weights broadcast to them (every
`actor_update_interval` updates) and return replay sequences plus episode outcomes. Outcomes of
the lowest-epsilon explorers (environment slots, see `TrainConfig.epsilon_per_env`) played
under the current task drive the curricula.

Training mix (`TrainConfig.task_mix` non-empty): the actors draw every episode's map kind, size
and agent count from the mix, in both stages (see `actor.py`); the trainer's task then carries
only alpha and its version. Stage 1 has no ladder: one pass of the success gate (same window and
threshold, measured on mix tasks at alpha 0) ends it (`ScaleCurriculum(single_gate=True)`), then
stage 2 runs the alpha curriculum on mix tasks. Success per setting is logged per map kind too.

Saved for a resume: weights, target, optimizer, curricula, counters, elapsed time
(train_state.pt, every few minutes) and the replay's sequences and priorities (replay.npz, when
the run stops and every `replay_interval_seconds`: a run resumed on a near-empty replay overfits
its first few hundred sequences). Lost: episodes in flight, and after kill -9 the experience
gathered since the last replay save.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import torch

from mapf_fleet.aliases import renamed_keys
from mapf_fleet.stop_signals import StopSignals
from mapf_fleet.version import code_version

from . import demos, run_state
from .actor import EpisodeWorker, Task
from .config import TrainConfig, config_from_dict, load_config, save_config
from .curriculum import AlphaCurriculum, ScaleCurriculum, SuccessWindow
from .learner import Learner
from .loop_report import STAGE_ALPHA, STAGE_DONE, STAGE_SCALE, Pace, warm_start_bar, write_scalars
from .modelio import hidden_dim
from .ray_pool import CpuMeter, make_pool
from .replay import PrioritizedSequenceReplay
from .run_state import earlier_overrides, resumed_config  # noqa: F401 (the trainer's API)

# counters copied into every checkpoint's metadata (extra.counters)
CHECKPOINT_COUNTERS = ("elapsed_seconds", "cpu_seconds", "cpu_measured_from_elapsed_seconds",
                       "demo_seconds", "episodes", "env_steps", "agent_steps")


def actor_pool(cfg: TrainConfig):
    """The Ape-X actors: `num_actors` EpisodeWorkers in the shared worker pool (ray_pool.py)."""
    return make_pool(EpisodeWorker, [(cfg, i) for i in range(cfg.num_actors)], cfg.use_ray,
                     cfg.ray_address, cfg.num_cpus)


class Trainer:
    def __init__(self, cfg: TrainConfig, run_dir: str | Path, resume: bool = False,
                 restore_replay: bool = True, session_overrides: dict | None = None):
        self.cfg, self.run_dir = cfg, Path(run_dir)
        # `--resume RUN --set F=V`: fields changed from this session on; config.yaml keeps the
        # run's starting config, the change goes on this session's record
        self.session_overrides = dict(session_overrides) if session_overrides else None
        self.run_dir.mkdir(parents=True, exist_ok=True)
        torch.manual_seed(cfg.seed)
        torch.set_num_threads(cfg.learner_threads)
        self.learner = Learner(cfg)
        self.replay = PrioritizedSequenceReplay(
            cfg.replay_capacity, cfg.window_len, cfg.seq_len, cfg.final_agents,
            hidden_dim(self.learner.model), cfg.priority_alpha, cfg.priority_epsilon, cfg.seed)
        self.scale = ScaleCurriculum(cfg.start_agents, cfg.start_map_size, cfg.final_agents,
                                     cfg.final_map_size, cfg.map_size_step, cfg.success_window,
                                     cfg.success_threshold, single_gate=bool(cfg.task_mix))
        self.alpha = AlphaCurriculum(cfg.alpha_mode, cfg.alpha_step, cfg.alpha_max,
                                     cfg.fixed_alpha, cfg.success_window, cfg.success_threshold,
                                     cfg.alpha_max_updates, cfg.plateau_windows,
                                     cfg.plateau_min_delta, cfg.alpha_min_updates)
        self.stage = STAGE_SCALE
        self.task_version = 0
        self.counters = {"episodes": 0, "gate_episodes": 0, "agent_steps": 0, "env_steps": 0,
                         "elapsed_seconds": 0.0, "added_sequences": 0, "sampled_sequences": 0}
        self.checkpoints: list[str] = []
        self.gate_actors = set(cfg.gate_actor_indices())
        # success of every setting / alpha seen, for the logs (not used for gating)
        self.setting_windows: dict[str, SuccessWindow] = {}
        self.events: list[str] = []
        # the code of every session that trained this run (a resume may run newer code)
        self.code_versions: list[dict] = []
        self.bar = None
        self.bar_actor_rate: float | None = None  # last actor rate shown on the bar
        if resume:
            self._load_state()
            if restore_replay:
                self._restore_replay()
        else:
            if cfg.init_checkpoint:
                self._load_init_checkpoint(cfg.init_checkpoint)
            save_config(cfg, self.run_dir / run_state.CONFIG_FILE)
        if self.stage == STAGE_SCALE and self.scale.done:
            self._enter_stage_alpha(save=False)

    def _load_init_checkpoint(self, path: str) -> None:
        """Start from a checkpoint's weights (online and target); the network must match."""
        from mapf_fleet.models.checkpoint import CheckpointError, read_checkpoint
        from mapf_fleet.models.config import ModelConfig

        state, metadata = read_checkpoint(path)
        own = self.learner.model.config.to_dict()
        # through ModelConfig: fields newer than the file (observation) take their defaults
        theirs = ModelConfig.from_dict(metadata["model_config"]).to_dict()
        if metadata.get("algorithm") != self.cfg.algo or theirs != own:
            diff = sorted(k for k in set(own) | set(theirs) if own.get(k) != theirs.get(k))
            raise CheckpointError(
                f"{path}: init_checkpoint is a {metadata.get('algorithm')} network "
                f"{ {k: theirs.get(k) for k in diff} }, this run trains {self.cfg.algo} "
                f"{ {k: own.get(k) for k in diff} }")
        self.learner.model.load_state_dict(state)
        self.learner.sync_target()

    # -- state ----------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"learner": self.learner.state_dict(), "scale": self.scale.state_dict(),
                "alpha": self.alpha.state_dict(), "stage": self.stage,
                "task_version": self.task_version, "counters": dict(self.counters),
                "checkpoints": list(self.checkpoints), "config": self.cfg.to_dict(),
                "code_versions": list(self.code_versions)}

    def _load_state(self) -> None:
        state = run_state.load_state(self.run_dir)
        self.learner.load_state_dict(state["learner"])
        self.scale.load_state_dict(state["scale"])
        self.stage = str(state["stage"])
        if self.stage != STAGE_SCALE:
            before, now = (run_state.stage2_scheme(state.get("config", {})),
                          run_state.stage2_scheme(self.cfg.to_dict()))
            if before == now:
                # stage 2 has begun: its progress is restored. Before that it holds nothing yet
                # and is built from the config, so a resume with --set alpha_mode=... applies.
                self.alpha.load_state_dict(state["alpha"])
            else:
                # a fork that changes the stage-2 scheme (e.g. a fixed-alpha run resumed with
                # --set alpha_mode=curriculum): the old gate window, budget and alpha* belong to
                # the other scheme, so stage 2 starts again from the config on these weights
                self.stage = STAGE_DONE if self.alpha.done else STAGE_ALPHA
                self.alpha.begin(self.learner.updates)
                self._log_event(f"stage 2 restarted: {before} -> {now} (learned weights kept)")
        self.task_version = int(state["task_version"]) + 1  # episodes in flight are gone
        self.counters.update(state["counters"])
        self.checkpoints = list(state["checkpoints"])
        self.code_versions = list(state.get("code_versions", []))

    def save_state(self) -> None:
        run_state.save_state(self.run_dir, self.state_dict())

    def save_replay(self) -> None:
        run_state.save_replay(self.run_dir, self.replay.state_dict())

    def _restore_replay(self) -> None:
        """Reload RUN/replay.npz when it fits this run's replay; otherwise say why and start
        with an empty replay (the file is left in place)."""
        try:
            state = run_state.load_replay(self.run_dir)
            if state is not None:
                self.replay.load_state_dict(state)
                self._log_event(f"replay restored: {len(self.replay)} sequences")
        except (ValueError, KeyError) as err:
            self._log_event(f"replay not restored, starting empty: {err}")
            logging.getLogger(__name__).warning("replay not restored, starting empty: %s", err)

    # -- curriculum -------------------------------------------------------------------------------
    @property
    def task(self) -> Task:
        if self.stage == STAGE_SCALE:
            return Task(self.scale.num_agents, self.scale.map_size, 0.0, self.task_version)
        return Task(self.cfg.final_agents, self.cfg.final_map_size, float(self.alpha.alpha),
                    self.task_version)

    def _metadata(self) -> dict:
        curriculum = {"stage": self.stage, "setting": list(self.scale.setting),
                      "alpha_passed": list(self.alpha.passed), "alpha_star": self.alpha.alpha_star}
        if self.cfg.task_mix:  # the tasks came from the mix, not from `setting`
            curriculum["task_mix"] = dict(self.cfg.task_mix)
        meta = {"alpha": float(self.task.alpha),
                "curriculum": curriculum,
                "learner_steps": int(self.learner.updates),
                "training_config": self.cfg.to_dict(),
                "extra": {"trained_with_code": list(self.code_versions),
                          # the compute spent up to this checkpoint (cards, side-by-side tables)
                          "counters": {k: self.counters[k] for k in CHECKPOINT_COUNTERS
                                       if k in self.counters}}}
        if self.cfg.conflict_rule != "revert":
            # trained behind the shield under this ranking: the evaluator and the policy nodes
            # rank with it under that rule unless told otherwise (as DAgger's checkpoints do)
            meta["rankings"] = {self.cfg.conflict_rule: self.cfg.ranking}
        meta["guidance"] = self.cfg.guidance  # the heuristic channels it learned to read
        return meta

    def save_checkpoint(self, name: str, alpha: float | None = None) -> Path:
        from mapf_fleet.models.checkpoint import save_checkpoint

        meta = self._metadata()
        if alpha is not None:
            meta["alpha"] = float(alpha)
        path = self.run_dir / run_state.CHECKPOINT_DIR / name
        save_checkpoint(path, self.learner.model, meta)
        if name not in self.checkpoints:
            self.checkpoints.append(name)
        return path

    def _enter_stage_alpha(self, save: bool = True) -> None:
        if save:
            self.save_checkpoint("stage1.pt", alpha=0.0)
        self.stage = STAGE_DONE if self.alpha.done else STAGE_ALPHA
        self.alpha.begin(self.learner.updates)
        self.task_version += 1

    def _record_episode(self, ep: dict) -> None:
        self.counters["episodes"] += 1
        key = f"{ep['num_agents']}agents_{ep['map_size']}x{ep['map_size']}_alpha{ep['alpha']:.1f}"
        if self.cfg.task_mix:
            key = f"{ep.get('map_kind', 'random')}_{key}"
        self.setting_windows.setdefault(key, SuccessWindow(self.cfg.success_window)).add(
            ep["success"])
        gate = ep["gate"] if "gate" in ep else ep["actor"] in self.gate_actors
        if not gate or ep["task_version"] != self.task_version:
            return
        self.counters["gate_episodes"] += 1
        if self.stage == STAGE_SCALE:
            if self.scale.record(ep["success"]):
                self.task_version += 1
                self._log_event("stage 1: the training mix passed the gate" if self.cfg.task_mix
                                else f"stage 1: setting -> {self.scale.setting}")
                if self.scale.done:
                    self._enter_stage_alpha()
        elif self.stage == STAGE_ALPHA:
            alpha_now = self.alpha.alpha
            event = self.alpha.record(ep["success"], self.learner.updates)
            if event == AlphaCurriculum.PASSED:
                self.save_checkpoint(run_state.alpha_checkpoint_name(alpha_now), alpha=alpha_now)
                self.task_version += 1
                self._log_event(f"stage 2: alpha {alpha_now:g} passed")
            if self.alpha.done:
                self.stage = STAGE_DONE
                self._log_event(f"stage 2 done: {self.alpha.stop_reason}")

    def _replay_ratio_allows(self) -> bool:
        """One more batch keeps sampled / added sequences within `max_replay_ratio` (0: no
        limit). Counted from this run's replay only (warm-start demo updates do not count)."""
        ratio = self.cfg.max_replay_ratio
        if ratio <= 0:
            return True
        sampled = self.counters["sampled_sequences"] + self.cfg.batch_size
        return sampled <= ratio * self.counters["added_sequences"]

    def _log_event(self, text: str) -> None:
        self.events.append(f"[update {self.learner.updates}] {text}")
        if self.bar is not None:
            self.bar.write(text)

    # -- main loop --------------------------------------------------------------------------------
    stop_signal: str = ""
    _stops: StopSignals | None = None  # the run's stop signals (`_catch_stop_signals`)

    def _catch_stop_signals(self):
        """Ctrl-C / SIGTERM: finish the current update, save state and the final checkpoint, and
        return (`_stop_reason`; more signals change nothing: the handler only sets a flag, so a
        burst of them cannot hang the run; kill -9 and --resume for an abort). Called again
        after ray.init, which installs its own handlers. Returns a function restoring the old
        handlers."""
        if threading.current_thread() is not threading.main_thread():
            return lambda: None
        if self._stops is None:
            self._stops = StopSignals().install()
            return self._stops.restore
        self._stops.reinstall()
        return lambda: None

    def run(self) -> dict:
        """Ape-X (Horgan et al. 2018) under the paper's curricula: actors play the current task
        with the latest weights into a prioritized replay; the learner samples it, updates the
        network and the priorities and broadcasts its weights every `actor_update_interval`
        updates; the gate actors' episodes move the curricula until stage 2 is done."""
        cfg = self.cfg
        writer = self._begin_session()
        restore_early = self._catch_stop_signals()  # honoured once the loop starts
        cpu, cpu0 = CpuMeter(), self._cpu_seconds_so_far()
        self._demo_warm_start(writer, cpu, cpu0)
        actors = actor_pool(cfg)
        restore_signals = self._catch_stop_signals()  # after ray.init, which installs its own
        pace, stats = Pace(self.counters, cpu, cpu0, self.learner.updates), {}
        actors.broadcast(self.learner.cpu_weights(), self.learner.updates)
        stop_reason = ""
        try:
            while self.stage != STAGE_DONE and not (stop_reason := self._stop_reason(pace)):
                # 1. actors: experience into the replay, finished episodes into the curricula
                block = not (self._learning_started() and self._replay_ratio_allows())
                for result in self._play(actors, block):
                    pace.steps += self._absorb(result, cpu)
                    if self.stage == STAGE_DONE:
                        break
                if self.stage == STAGE_DONE:
                    break
                # 2. learner: prioritized replay -> n-step double-Q update -> new priorities
                if self._learning_started():
                    for _ in range(cfg.updates_per_poll):
                        if self._demo_turn():
                            demos.demo_update(self.learner, self.demo_replay, cfg, writer)
                        elif not self._replay_ratio_allows():
                            break  # the actors first: poll again (blocking) for new sequences
                        else:
                            batch = self.replay.sample(cfg.batch_size, cfg.priority_beta)
                            priorities, stats = self.learner.update(batch)
                            self.replay.update_priorities(batch.indices, priorities)
                            self.counters["sampled_sequences"] += cfg.batch_size
                        pace.updates += 1
                        if self.bar is not None:
                            self.bar.update(1)
                        # 3. the actors get the new weights every actor_update_interval updates
                        if self.learner.updates % cfg.actor_update_interval == 0:
                            actors.broadcast(self.learner.cpu_weights(), self.learner.updates)
                    self._check_stage2_budget()
                # 4. logs, state and replay saves when due
                self._bookkeeping(writer, pace, stats)
        finally:
            restore_signals()
            restore_early()
            actors.close()
            pace.tick()
            if self.bar is not None:
                self.bar.close()
        return self._finish(stop_reason, writer)

    # -- the loop's helpers ---------------------------------------------------------------------
    def _begin_session(self):
        """TensorBoard writer (None without tensorboard), progress bar, and this session's entry
        in the run's record of code versions."""
        writer = None
        try:
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(str(self.run_dir / run_state.TB_DIR))
        except ImportError:  # tensorboard missing: train anyway, say so
            logging.getLogger(__name__).warning("tensorboard not installed: no scalars written")
        if self.cfg.progress_bar:
            from tqdm import tqdm

            self.bar = tqdm(total=self.cfg.max_updates, initial=self.learner.updates, unit="upd",
                            dynamic_ncols=True)
        self.demo_replay = None
        session = {**code_version(), "from_update": int(self.learner.updates)}
        if self.session_overrides:
            session["overrides"] = dict(self.session_overrides)
            self._log_event(f"resumed with overrides {self.session_overrides}")
        self.code_versions.append(session)
        return writer

    def _cpu_seconds_so_far(self) -> float:
        if "cpu_seconds" not in self.counters:  # runs begun before CPU time was measured
            self.counters["cpu_seconds"] = 0.0
            self.counters["cpu_measured_from_elapsed_seconds"] = self.counters["elapsed_seconds"]
        return self.counters["cpu_seconds"]

    def _demo_warm_start(self, writer, cpu: CpuMeter, cpu0: float) -> None:
        """The demonstration warm start (demos.py), before any actor plays: the first broadcast
        then carries the warm-started weights. With `demo_interleave` the demonstrations stay
        for the curricula's demo updates."""
        cfg = self.cfg
        pretrained = bool(self.counters.get("demo_pretrained"))
        if cfg.demo_source == "none" or (pretrained and not cfg.demo_interleave):
            return
        # The learner keeps learner_threads meanwhile: more threads than free cores (another run
        # on the machine) made oneDNN's thread barrier many times slower.
        demo_start = time.monotonic()
        self.demo_replay, info = demos.make_demo_replay(self.learner, cfg, log=self._log_event)
        summary = None
        if not pretrained:
            summary = demos.pretrain(self.learner, cfg, writer, replay=self.demo_replay,
                                     on_update=lambda stats: warm_start_bar(self, stats))
            summary.update({k: v for k, v in info.items() if k != "settings"})
            self.counters["demo_pretrained"] = 1
        # demonstrations (and the warm start) are part of the run's compute (cards' CPU-hours)
        spent = time.monotonic() - demo_start
        self.counters["demo_seconds"] = self.counters.get("demo_seconds", 0.0) + spent
        self.counters["elapsed_seconds"] += spent
        self.counters["cpu_seconds"] = cpu0 + cpu.seconds()
        if summary is not None:
            self._log_event(f"demo warm start done in {spent:.0f} s: {summary}")
            self.save_checkpoint("demo_warm_start.pt", alpha=0.0)
            self.save_state()
        if not cfg.demo_interleave:
            self.demo_replay = None

    def _stop_reason(self, pace: Pace) -> str:
        """Why the loop stops now ("" = go on)."""
        cfg = self.cfg
        if self.learner.updates >= cfg.max_updates:
            return f"max_updates {cfg.max_updates} reached"
        if not self.stop_signal and self._stops is not None and self._stops.requested:
            self.stop_signal = self._stops.name
            self._log_event(f"{self.stop_signal}: stopping after this update, saving state")
        if self.stop_signal:
            return f"stopped by {self.stop_signal} (resume with --resume)"
        if cfg.max_wall_seconds and pace.wall() >= cfg.max_wall_seconds:
            return f"max_wall_seconds {cfg.max_wall_seconds:g} reached"
        return ""

    def _learning_started(self) -> bool:
        return self.replay.added_steps >= self.cfg.learning_starts and len(self.replay) > 0

    def _play(self, actors, block: bool) -> list[dict]:
        """Keep every idle actor playing the current task; the calls that finished."""
        steps = self.cfg.actor_steps_per_call
        for index in actors.idle():
            actors.submit(index, "play", self.task, steps)
        results = [result for _, result in actors.ready(block)]
        if actors.in_background:  # Ray actors play on while the learner updates
            for index in actors.idle():
                actors.submit(index, "play", self.task, steps)
        return results

    def _absorb(self, result: dict, cpu: CpuMeter) -> int:
        """One actor call's sequences into the replay and episodes into the curricula; returns
        its agent-steps."""
        cpu.actor_report(result)
        for seq in result["sequences"]:
            self.replay.add(seq)
        self.counters["added_sequences"] += len(result["sequences"])
        self.counters["agent_steps"] += result["agent_steps"]
        for ep in result["episodes"]:
            self.counters["env_steps"] += ep["steps"]
            self._record_episode(ep)
            if self.stage == STAGE_DONE:
                break
        return result["agent_steps"]

    def _demo_turn(self) -> bool:
        """With `demo_interleave` n, every n-th update trains on the demonstrations."""
        return (self.demo_replay is not None
                and (self.learner.updates + 1) % self.cfg.demo_interleave == 0)

    def _check_stage2_budget(self) -> None:
        if self.stage == STAGE_ALPHA and self.alpha.check_budget(self.learner.updates):
            self.stage = STAGE_DONE
            self._log_event(f"stage 2 done: {self.alpha.stop_reason}")

    def _bookkeeping(self, writer, pace: Pace, stats: dict) -> None:
        cfg = self.cfg
        now = pace.tick()
        if now - pace.last_log >= cfg.log_interval_seconds:
            self._write_scalars(writer, stats, pace.rates(now))
        if (self.learner.updates - pace.last_state >= cfg.state_interval_updates
                or now - pace.last_state_time >= cfg.state_interval_seconds):
            self.save_state()
            pace.last_state, pace.last_state_time = self.learner.updates, now
        if cfg.replay_interval_seconds and now - pace.last_replay >= cfg.replay_interval_seconds:
            self.save_replay()
            pace.last_replay = now

    def _finish(self, stop_reason: str, writer) -> dict:
        """The final checkpoint, state (and replay, unless finished) and result.json."""
        if self.stage == STAGE_DONE and not stop_reason:
            stop_reason = self.alpha.stop_reason or "stage 2 done"
        self.save_checkpoint("final.pt")
        self.save_state()
        if self.stage != STAGE_DONE:  # a finished run is not resumed
            self.save_replay()
        result = self.result(stop_reason)
        run_state.write_result(self.run_dir, result)
        if writer is not None:
            writer.close()
        return result

    def result(self, stop_reason: str) -> dict:
        return {"stage": self.stage, "finished": self.stage == STAGE_DONE,
                "stop_reason": stop_reason, "alpha_star": self.alpha.alpha_star,
                "alpha_passed": list(self.alpha.passed), "setting": list(self.scale.setting),
                "learner_updates": self.learner.updates, "checkpoints": list(self.checkpoints),
                "counters": dict(self.counters), "events": list(self.events)}

    def _write_scalars(self, writer, stats: dict, rates: dict) -> None:
        write_scalars(self, writer, stats, rates)


def train(config_path: str | Path | None = None, run_dir: str | Path | None = None,
          resume: str | Path | None = None, overrides: dict | None = None) -> dict:
    """Start (config + run_dir) or resume (run dir) a training run; returns the result."""
    if resume is not None:
        run_dir = Path(resume)
        cfg = resumed_config(run_dir)
    else:
        if config_path is None or run_dir is None:
            raise ValueError("train: give config_path and run_dir, or resume")
        cfg = load_config(config_path)
    if overrides:  # the CLI warned once about a deprecated key: read it quietly here
        overrides = renamed_keys(overrides, "overrides", quiet=True)
        cfg = config_from_dict({**cfg.to_dict(), **overrides}, source="overrides")
    return Trainer(cfg, run_dir, resume=resume is not None,
                   session_overrides=overrides if resume is not None else None).run()
