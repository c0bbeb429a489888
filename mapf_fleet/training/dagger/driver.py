"""The DAgger driver: rounds of collect (the workers play and label), aggregate (shards and their
manifest), train (on every round's labels) and the held-out check, resumable at any point.

Run directory: `config.yaml`; `state.json` / `state.pt` (the round and phase, collect / train /
heldout, the counters, the network and optimiser; training progress within a round is saved every
`state_interval_seconds`); `data/` (the shards and `manifest.json`, recorded after its file; a
resumed run skips the shards in the manifest and adopts a shard file the manifest missed);
`checkpoints/round_{k}.pt`; `curve.json` / `curve.csv` and TensorBoard (`tb/`). After kill -9 a
run loses at most the episodes in flight and the updates since the last state save."""

from __future__ import annotations

import json
import os
import time
import zipfile
from pathlib import Path

import numpy as np
import torch
import yaml

from mapf_fleet.files import atomic_write
from mapf_fleet.models.policy import resolve_device
from mapf_fleet.stop_signals import StopSignals

from ..ray_pool import make_pool
from .config import DaggerConfig, DaggerConfigError
from .data import (SHARD_COUNTERS, LabelledData, read_shard, shard_name, window_loss,
                   write_json, write_shard)
from .rollout import DaggerWorker, kind_code

CONFIG_FILE = "config.yaml"
STATE_JSON = "state.json"
STATE_PT = "state.pt"
DATA_DIR = "data"
MANIFEST = "manifest.json"
CURVE_JSON = "curve.json"
CURVE_CSV = "curve.csv"
CHECKPOINT_DIR = "checkpoints"
TB_DIR = "tb"
PHASES = ("collect", "train", "heldout")


class Dagger:
    def __init__(self, cfg: DaggerConfig, run_dir: str | Path, log=print):
        from mapf_fleet.models.checkpoint import load_checkpoint, with_observation

        self.cfg, self.run_dir, self.log = cfg, Path(run_dir), log
        self.run_dir.mkdir(parents=True, exist_ok=True)
        (self.run_dir / DATA_DIR).mkdir(exist_ok=True)
        torch.manual_seed(cfg.seed)
        torch.set_num_threads(cfg.threads)
        self.device = resolve_device(cfg.device)
        model, meta = load_checkpoint(cfg.init_checkpoint)
        if cfg.observation is not None:
            try:
                model = with_observation(model, cfg.observation)
            except ValueError as exc:
                raise DaggerConfigError(
                    f"field 'observation' = {cfg.observation!r}: the init checkpoint "
                    f"{cfg.init_checkpoint} reads {model.config.observation!r}: {exc}") from None
        self.init_metadata = meta
        self.algo = meta["algorithm"]
        self.model_config = model.config.to_dict()  # the workers' network, observation included
        self.model = model.to(self.device)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=cfg.lr)
        self.state = {"round": 0, "phase": "collect", "updates_in_round": 0, "updates": 0,
                      "counters": {"episodes": 0, "labelled_states": 0, "labels": 0,
                                   "unsolved": 0, "too_long": 0, "expert_steps": 0,
                                   "label_seconds": 0.0, "disagree": 0, "disagree_off_goal": 0,
                                   "off_goal_labels": 0, "label_calls": 0, "cpu_seconds": 0.0,
                                   "elapsed_seconds": 0.0, "baseline_done": 0}}
        self.manifest = {"shards": {}}
        self.curve: list[dict] = []
        if (self.run_dir / STATE_JSON).is_file():
            self._load()
        else:
            atomic_write(self.run_dir / CONFIG_FILE,
                         lambda f: f.write(yaml.safe_dump(cfg.to_dict(), sort_keys=False).encode()))
        self.data = LabelledData(cfg.seq_len, cfg.burn_in, cfg.wait_label_cap)
        self._stops = StopSignals()
        self._cpu_last: dict[int, float] = {}

    # -- state --------------------------------------------------------------------------------
    def _load(self) -> None:
        self.state = json.loads((self.run_dir / STATE_JSON).read_text())
        saved = torch.load(self.run_dir / STATE_PT, map_location=self.device, weights_only=True)
        try:
            self.model.load_state_dict(saved["model"])
        except RuntimeError as exc:  # e.g. a resume that changes field 'observation'
            raise DaggerConfigError(
                f"{self.run_dir / STATE_PT}: the run's network is not the one this config builds "
                f"(field 'observation' = {self.cfg.observation!r}, init checkpoint "
                f"{self.cfg.init_checkpoint}): {str(exc).splitlines()[0]}") from None
        self.optimizer.load_state_dict(saved["optimizer"])
        manifest = self.run_dir / DATA_DIR / MANIFEST
        if manifest.is_file():
            self.manifest = json.loads(manifest.read_text())
        curve = self.run_dir / CURVE_JSON
        if curve.is_file():
            self.curve = json.loads(curve.read_text())
        self.log(f"resumed: round {self.state['round']} phase {self.state['phase']} "
                 f"({self.state['updates_in_round']} updates into the round), "
                 f"{len(self.manifest['shards'])} shards")

    def save_state(self) -> None:
        atomic_write(self.run_dir / STATE_PT, lambda f: torch.save(
            {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict()}, f))
        write_json(self.run_dir / STATE_JSON, self.state)

    def _cpu(self, result: dict) -> None:
        """Worker CPU seconds (another process) into the counters; the driver's own are added
        by `_tick`."""
        pid, total = result.get("pid"), result.get("process_cpu_seconds")
        if pid is None or pid == os.getpid():
            return
        self.state["counters"]["cpu_seconds"] += max(0.0, total - self._cpu_last.get(pid, 0.0))
        self._cpu_last[pid] = total

    def _tick(self) -> None:
        now, cpu = time.monotonic(), time.process_time()
        c = self.state["counters"]
        c["elapsed_seconds"] += now - self._wall
        c["cpu_seconds"] += cpu - self._proc
        self._wall, self._proc = now, cpu

    def weights(self) -> dict:
        return {k: v.detach().to("cpu").clone() for k, v in self.model.state_dict().items()}

    # -- phases -----------------------------------------------------------------------------------
    def jobs(self, round_index: int) -> list[dict]:
        cfg = self.cfg
        tasks = cfg.round_tasks(round_index)
        weights = np.array([float(t.get("weight", 1.0)) for t in tasks])
        rng = np.random.default_rng([cfg.seed, 7, round_index])
        jobs = []
        for e in range(cfg.episodes_per_round):
            task = tasks[int(rng.choice(len(tasks), p=weights / weights.sum()))]
            agents = int(task["agents"][int(rng.integers(len(task["agents"])))])
            jobs.append({"round": round_index, "episode": e, "beta": cfg.beta(round_index),
                         "task": {"kind": task["kind"], "size": int(task["size"]),
                                  "agents": agents, "max_steps": int(task["max_steps"])},
                         "seed_words": [cfg.seed, round_index, e, kind_code(task["kind"])]})
        return jobs

    def collect(self, workers, round_index: int) -> None:
        data_dir = self.run_dir / DATA_DIR
        todo = []
        for job in self.jobs(round_index):
            name = shard_name(round_index, job["episode"])
            if name in self.manifest["shards"] and (data_dir / name).is_file():
                continue
            if (data_dir / name).is_file():  # killed between the shard and the manifest
                try:
                    _, meta = read_shard(data_dir / name)
                    self._record_shard(name, meta)
                    continue
                except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError):
                    pass  # a damaged file: play it again
            todo.append(job)
        if not todo:
            return
        self.log(f"round {round_index}: playing {len(todo)} episodes (beta {self.cfg.beta(round_index):.3f})")
        for result in workers.map("collect", todo):
            self._cpu(result)
            job = result["job"]
            name = shard_name(job["round"], job["episode"])
            arrays = result.pop("arrays")
            meta = {k: v for k, v in result.items() if k not in ("pid", "process_cpu_seconds")}
            meta["file"] = name
            write_shard(data_dir / name, arrays, meta)
            self._record_shard(name, meta)
            self._tick()
            t = job["task"]
            self.log(f"  {name}: {t['kind']} {t['size']} {t['agents']} agents: "
                     f"{'solved' if meta['success'] else 'failed'} in {meta['steps']} steps, "
                     f"{meta['labelled_states']} states labelled ({meta['labels']} labels), "
                     f"{meta['unsolved']} unsolved, {meta['too_long']} too long, "
                     f"{meta['label_seconds']:.1f} s LaCAM")
            if self.stop_signal:
                break

    def _record_shard(self, name: str, meta: dict) -> None:
        self.manifest["shards"][name] = meta
        write_json(self.run_dir / DATA_DIR / MANIFEST, self.manifest)
        # the data counters are sums over the manifest: right whenever a kill fell
        c, shards = self.state["counters"], self.manifest["shards"].values()
        c["episodes"] = len(self.manifest["shards"])
        for key in SHARD_COUNTERS:
            c[key] = sum(m[key] for m in shards)
        c["label_calls"] = sum(m.get("label_calls", 0) for m in shards)
        self.save_state()

    def load_data(self) -> None:
        observation = self.model.config.observation
        for name in sorted(self.manifest["shards"]):
            if name not in self.data.names:
                path = self.run_dir / DATA_DIR / name
                arrays, _ = read_shard(path)
                recorded = "cost_to_go" if "ctg" in arrays else "paper"
                if recorded != observation:
                    raise DaggerConfigError(
                        f"{path}: holds {recorded!r} observations, the network reads "
                        f"{observation!r}: field 'observation' changed during the run")
                self.data.add(name, arrays)

    def train(self, round_index: int, writer=None) -> dict:
        cfg = self.cfg
        self.load_data()
        if not self.data.windows:
            self.log(f"round {round_index}: no labelled windows yet, no training")
            return {}
        rng = np.random.default_rng([cfg.seed, 11, round_index, self.state["updates_in_round"]])
        self.model.train()
        last_save = time.monotonic()
        stats = {"loss": [], "agreement": []}
        while self.state["updates_in_round"] < cfg.updates_per_round and not self.stop_signal:
            picks = rng.integers(len(self.data.windows), size=cfg.batch_windows)
            wins = [self.data.window(*self.data.windows[p]) for p in picks]
            total = sum(float((w["labels"][w["burn"]:] >= 0).sum()) for w in wins)
            self.optimizer.zero_grad(set_to_none=True)
            loss_sum = agree_sum = 0.0
            for w in wins:
                value, count, agree = window_loss(self.model, self.algo, w, self.device,
                                                  cfg.loss, cfg.margin)
                if count:
                    (value / total).backward()
                loss_sum += float(value.detach())
                agree_sum += agree
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), cfg.grad_clip)
            self.optimizer.step()
            self.state["updates_in_round"] += 1
            self.state["updates"] += 1
            stats["loss"].append(loss_sum / max(total, 1.0))
            stats["agreement"].append(agree_sum / max(total, 1.0))
            if writer is not None:
                writer.add_scalar("learner/loss", stats["loss"][-1], self.state["updates"])
                writer.add_scalar("learner/agreement", stats["agreement"][-1], self.state["updates"])
            if time.monotonic() - last_save >= cfg.state_interval_seconds:
                self._tick()
                self.save_state()
                last_save = time.monotonic()
        self.model.eval()
        self._tick()
        summary = {}
        if stats["loss"]:
            k = max(1, len(stats["loss"]) // 5)
            summary = {"loss_first": float(np.mean(stats["loss"][:k])),
                       "loss_last": float(np.mean(stats["loss"][-k:])),
                       "agreement_last": float(np.mean(stats["agreement"][-k:]))}
        return summary

    def checkpoint(self, round_index: int, train_summary: dict) -> Path:
        from mapf_fleet.models.checkpoint import save_checkpoint

        c = self.state["counters"]
        meta = {"alpha": float(self.init_metadata.get("alpha", 0.0)),
                "curriculum": {"stage": "dagger", "round": round_index},
                "learner_steps": int(self.init_metadata.get("learner_steps", 0))
                + int(self.state["updates"]),
                "training_config": {"dagger": self.cfg.to_dict(),
                                    "init_training_config": self.init_metadata.get("training_config")},
                "extra": {"dagger": {"round": round_index, "updates": int(self.state["updates"]),
                                     "labels": int(c["labels"]),
                                     "labelled_states": int(c["labelled_states"]),
                                     "episodes": int(c["episodes"]),
                                     "unsolved": int(c["unsolved"]), "too_long": int(c["too_long"]),
                                     "cpu_seconds": round(float(c["cpu_seconds"]), 1),
                                     "init_checkpoint": self.cfg.init_checkpoint,
                                     "train": train_summary}},
                # the states it learned from were visited under this ranking behind this rule:
                # the evaluator and the policy nodes rank with it there unless told otherwise
                "rankings": {self.cfg.conflict_rule: self.cfg.ranking},
                # and read these heuristic channels: the evaluator's default guidance for it
                "guidance": self.cfg.guidance}
        return save_checkpoint(self.run_dir / CHECKPOINT_DIR / f"round_{round_index:03d}.pt",
                               self.model, meta)

    def heldout(self, workers, label: str, round_index: int, heuristic: bool = False) -> dict:
        cfg = self.cfg
        jobs = []
        for setting in cfg.heldout:
            for i in range(cfg.heldout_count):
                jobs.append({"task": dict(setting), "heuristic": heuristic,
                             "seed_words": [cfg.heldout_seed, kind_code(setting["kind"]),
                                            setting["size"], setting["agents"], i]})
        rows: dict[str, list] = {}
        for result in workers.map("heldout", jobs):
            self._cpu(result)
            t = result["job"]["task"]
            rows.setdefault(f"{t['kind']}{t['size']}_{t['agents']}", []).append(result)
        self._tick()
        entry = {"round": round_index, "policy": label, "updates": int(self.state["updates"]),
                 "labels": int(self.state["counters"]["labels"]),
                 "cpu_seconds": round(float(self.state["counters"]["cpu_seconds"]), 1)}
        for key, results in rows.items():
            entry[f"{key}_success"] = float(np.mean([r["success"] for r in results]))
            entry[f"{key}_steps"] = float(np.mean([r["steps"] for r in results]))
        return entry

    def _write_curve(self, writer=None) -> None:
        write_json(self.run_dir / CURVE_JSON, self.curve)
        keys = list(dict.fromkeys(k for row in self.curve for k in row))
        lines = [",".join(keys)] + [",".join(str(row.get(k, "")) for k in keys) for row in self.curve]
        atomic_write(self.run_dir / CURVE_CSV, lambda f: f.write(("\n".join(lines) + "\n").encode()))
        if writer is not None and self.curve:
            row = self.curve[-1]
            for k, v in row.items():
                if k.endswith(("_success", "_steps")):
                    writer.add_scalar(f"heldout_{row['policy']}/{k}", v, row["round"])

    def _catch_signals(self):
        """SIGINT / SIGTERM: the round's work stops at its next check (`stop_signal`), the
        state is saved. The handler only sets a flag (a burst of signals cannot hang the run).
        Returns a function restoring the old handlers."""
        self._stops.install()
        return self._stops.restore

    @property
    def stop_signal(self) -> str | None:
        """The first stop signal's name (None: none came)."""
        return self._stops.name or None

    def run(self) -> dict:
        cfg = self.cfg
        writer = None
        try:
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(str(self.run_dir / TB_DIR))
        except ImportError:
            self.log("tensorboard not installed: no scalars written")
        self._wall, self._proc = time.monotonic(), time.process_time()
        workers = make_pool(DaggerWorker, [(cfg, self.model_config)] * cfg.num_workers,
                            cfg.use_ray, cfg.ray_address, cfg.num_cpus)
        restore = self._catch_signals()
        try:
            if not self.state["counters"].get("baseline_done"):
                workers.broadcast(self.weights(), "init")
                for label, heuristic in (("plain_pibt", True), ("init", False)):
                    entry = self.heldout(workers, label, -1, heuristic)
                    self.curve.append(entry)
                    self._write_curve(writer)
                    self.log(f"held-out {label}: {entry}")
                self.state["counters"]["baseline_done"] = 1
                self.save_state()
            while self.state["round"] < cfg.rounds and not self.stop_signal:
                k = self.state["round"]
                if self.state["phase"] == "collect":
                    workers.broadcast(self.weights(), k)
                    self.collect(workers, k)
                    if self.stop_signal:
                        break
                    self.state["phase"], self.state["updates_in_round"] = "train", 0
                    self.save_state()
                if self.state["phase"] == "train":
                    summary = self.train(k, writer)
                    if self.stop_signal:
                        self.save_state()
                        break
                    self.state["train_summary"] = summary
                    self.checkpoint(k, summary)
                    self.state["phase"] = "heldout"
                    self.save_state()
                    self.log(f"round {k}: trained {self.state['updates_in_round']} updates on "
                             f"{len(self.data.windows)} windows: {summary}")
                if self.state["phase"] == "heldout":
                    workers.broadcast(self.weights(), f"{k}-trained")
                    entry = self.heldout(workers, "dagger", k)
                    entry.update({f"train_{a}": b for a, b in self.state.get("train_summary", {}).items()})
                    self.curve = [r for r in self.curve if not (r["round"] == k and r["policy"] == "dagger")]
                    self.curve.append(entry)
                    self._write_curve(writer)
                    self.log(f"held-out round {k}: {entry}")
                    self.state["round"], self.state["phase"] = k + 1, "collect"
                    self.state["updates_in_round"] = 0
                    self._tick()
                    self.save_state()
        finally:
            restore()
            workers.close()
            self._tick()
            self.save_state()
            if writer is not None:
                writer.close()
        reason = f"stopped by {self.stop_signal}" if self.stop_signal else "rounds done"
        self.log(f"{reason}: round {self.state['round']}, counters {self.state['counters']}")
        return {"round": self.state["round"], "phase": self.state["phase"], "stop": reason,
                "counters": dict(self.state["counters"])}


