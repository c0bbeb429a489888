"""DAgger behind the fleet's arbiter (issue 25): roll the policy out under the PIBT shield, have
LaCAM label every agent's next move at the visited joint states, aggregate, retrain, repeat.

    mapf-fleet dagger --config config/training/dagger_dcc.yaml --run-dir runs/dagger_dcc
    mapf-fleet dagger --run-dir runs/dagger_dcc          # resume (after a stop or kill -9)

Round k (k = 0, 1, ...):
  1. collect: `episodes_per_round` episodes drawn from the task list (`tasks`, plus `late_tasks`
     from round `late_tasks_from`), each played by the round's policy (the init checkpoint in
     round 0, else round k-1's weights) under `shield` (PIBT with the anchor by default, the
     fleet's arbiter) with its Q-values ranked by `preferences`. At every `label_interval`-th
     step (backing off after states it cannot label, `label_backoff_max`) the expert labels the
     joint state: LaCAM (pymapf, `coordination.planners.
     ClassicalPlanner`, `label_time_limit` seconds per connected region) from the agents'
     current cells to their goals; the label of agent i is the first move of its plan. DAgger's
     mixing: with probability beta_k = `beta0` * `beta_decay`^k (per labelled step) the shield
     executes the expert's ranking (its move first, then the distance order) instead of the
     policy's. A state is skipped (no labels; counted) when LaCAM leaves any agent unplanned
     within the limit ("unsolved") or when its plan is far longer than needed ("too_long":
     makespan > min(the task's step limit, `max_plan_factor` x the longest BFS distance of any
     agent to its goal + `max_plan_slack`)): a first-found plan of 800-2,200 steps (measured,
     issue 25) spends its first moves wandering, a poor label. Episodes are played by
     `num_workers` workers: Ray actors (local Ray with `num_cpus`, or `ray_address`), or
     in-process (`use_ray: false`). The driver waits while they play: collection and training
     never run at the same time, so a run uses about `num_cpus` cores.
  2. aggregate: each episode is one shard `data/r{round}_e{index}.npz` (observations as the
     policy saw them, bit-packed, and for the "cost_to_go" observation its cost-to-go channel
     beside them as int8 steps, `ctg`; positions; last-action inputs; labels, -1 = none; the
     policy's hidden state at every window start), recorded in `data/manifest.json` after its
     file; both written atomically. A resumed run skips the shards in the manifest (and adopts a
     shard file the manifest missed).
  3. train: `updates_per_round` updates on the aggregate of every round so far (DAgger). An update
     takes `batch_windows` windows sampled uniformly from all labelled windows: window j of an
     episode trains steps [j L, (j+1) L) (L = `seq_len`), unrolled from the hidden state the
     policy had at step j L - `burn_in` through `burn_in` steps without a loss (R2D2). The network
     sees exactly its inputs along the rollout (observations, positions, executed last actions:
     DCC's recurrent input is the executed move, as in the fleet). Loss on every agent of every
     labelled step: `loss` "cross_entropy" (softmax over the Q-head as logits) or "margin" (the
     DQfD large-margin loss of `demos.margin_loss`).
  4. checkpoint `checkpoints/round_{k}.pt` (the checkpoint format, atomic; metadata: round, labels,
     CPU seconds, `rankings` {shield: preferences}: the ranking it runs with by default) and the
     training state (`state.pt`, `state.json`), then the held-out check: `heldout` settings,
     `heldout_count` generated instances each (seeded apart from training; never the published
     test sets), success and average steps under the shield, appended to
     `curve.json` / `curve.csv` and TensorBoard (`tb/`). Before round 0 the same check runs on
     the init checkpoint (round -1) and on plain PIBT (the distance ranking, no network).

Observation (`observation`): the init checkpoint's unless set; "cost_to_go" on a "paper"
checkpoint adds the normalised cost-to-go channel (`grid.env.cost_to_go_channel`), warm-started
with that channel's first-conv weights zero (`models.checkpoint.with_observation`); the round
checkpoints record it in their `model_config`.

Resume: `state.json` names the round and phase (collect / train / heldout); training progress
within a round is saved every `state_interval_seconds`. After kill -9 a run loses at most the
episodes in flight and the updates since the last state save. CUDA is used when present
(`device: auto`); nothing needs it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from mapf_fleet.files import atomic_write

from .modelio import model_step, pick_device
from .replay import pack_cost_to_go, pack_obs, unpack_obs

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
SHARD_COUNTERS = ("labelled_states", "labels", "unsolved", "too_long", "expert_steps",
                  "label_seconds", "disagree", "disagree_off_goal", "off_goal_labels")
LOSSES = ("cross_entropy", "margin")


class DaggerConfigError(ValueError):
    """A DAgger configuration value is missing, unknown or out of range."""


def _default_tasks() -> list:
    return [
        # where the shipped default fails (issue 25): small crowded random maps, 128 steps
        {"kind": "dense", "size": 21, "agents": [32, 48, 64], "weight": 3.0, "max_steps": 128},
        {"kind": "random", "size": 40, "agents": [16, 32, 64], "weight": 2.0, "max_steps": 256},
        {"kind": "maze", "size": 40, "agents": [16, 32], "weight": 1.0, "max_steps": 256},
        {"kind": "rooms", "size": 40, "agents": [32, 64], "weight": 1.0, "max_steps": 256},
        {"kind": "warehouse", "size": 40, "agents": [32, 64], "weight": 1.0, "max_steps": 256},
    ]


def _default_late_tasks() -> list:
    return [{"kind": "random", "size": 80, "agents": [64], "weight": 1.0, "max_steps": 386}]


def _default_heldout() -> list:
    return [{"kind": "dense", "size": 21, "agents": 48, "max_steps": 128},
            {"kind": "random", "size": 40, "agents": 64, "max_steps": 256}]


@dataclass
class DaggerConfig:
    # --- policy ------------------------------------------------------------------------------
    # the checkpoint DAgger starts from (its network is kept: DCC or DHC as the paper built it)
    init_checkpoint: str = "models/default.pt"
    shield: str = "pibt_anchor"  # the arbiter the rollouts run under (coordination.pibt)
    # how the policy's Q-values become the ranking the shield reads (coordination.preferences);
    # q_then_distance is the best measured ranking under pibt_anchor (issue 25)
    preferences: str = "q_then_distance"
    # what the network reads (grid.env.OBSERVATIONS): None = the init checkpoint's; "cost_to_go"
    # from a "paper" checkpoint warm-starts it with the extra channel's weights zero
    # (models.checkpoint.with_observation), so round 0 plays exactly as the init checkpoint
    observation: str | None = None

    # --- rounds and data ---------------------------------------------------------------------
    rounds: int = 30
    episodes_per_round: int = 6
    tasks: list = field(default_factory=_default_tasks)  # {kind, size, agents: [..], weight, max_steps}
    late_tasks: list = field(default_factory=_default_late_tasks)  # added from late_tasks_from on
    late_tasks_from: int = 6
    beta0: float = 0.5  # DAgger mixing: round k executes the expert with probability beta0 * decay^k
    beta_decay: float = 0.5
    label_interval: int = 1  # label every n-th step of a rollout (1 = every step)
    # After a state LaCAM left mostly unlabelled (unsolved / too long for regions holding over
    # half the agents), the next label waits twice as
    # long as the last wait, up to this many steps; a labelled state resets it (1 = never
    # wait). Why: a deadlocked crowd stays unsolvable for LaCAM for many steps (measured,
    # round 0 of runs/dagger_dcc: 59-63 of 64 states of a dense 48/64-agent episode, ~0.5 s each).
    label_backoff_max: int = 16

    # --- expert --------------------------------------------------------------------------------
    label_time_limit: float = 0.5  # seconds of LaCAM per connected region
    max_plan_factor: float = 3.0  # a plan longer than factor x BFS lower bound + slack ...
    max_plan_slack: int = 32  # ... (or than the task's step limit) gives no labels
    planner_seed: int = 0

    # --- workers -------------------------------------------------------------------------------
    use_ray: bool = True  # False: episodes play in the driver process
    ray_address: str | None = None  # join this Ray cluster; None starts a local Ray
    num_cpus: int = 1  # CPUs of the local Ray
    num_workers: int = 1

    # --- learner -------------------------------------------------------------------------------
    # "margin" (DQfD) | "cross_entropy"; margin won the A/B of issue 25 at matched compute (8 rounds
    # each from the then default, models/archive/dcc_4x25_cl_alpha1.0.pt; docs/results.md)
    loss: str = "margin"
    margin: float = 0.8  # the large margin of loss "margin"
    lr: float = 5e-5
    grad_clip: float = 40.0
    seq_len: int = 16  # trained steps per window
    burn_in: int = 8  # steps unrolled without a loss before them
    batch_windows: int = 8  # windows per update (gradients accumulated)
    updates_per_round: int = 150
    device: str = "auto"  # "auto" = cuda when present, else cpu
    threads: int = 1  # torch threads of the driver and of each worker

    # --- held-out check --------------------------------------------------------------------------
    heldout: list = field(default_factory=_default_heldout)  # {kind, size, agents, max_steps}
    heldout_count: int = 10  # instances per held-out setting
    heldout_seed: int = 20_251_201  # instances drawn apart from every training seed

    # --- run -------------------------------------------------------------------------------------
    seed: int = 0
    state_interval_seconds: float = 120.0

    def __post_init__(self) -> None:
        self.validate()

    def validate(self, source: str = "DaggerConfig") -> None:
        from mapf_fleet.coordination.pibt import SHIELD_RULES
        from mapf_fleet.coordination.preferences import Q_MODES
        from mapf_fleet.grid.env import OBSERVATIONS

        def bad(name: str, why: str) -> DaggerConfigError:
            return DaggerConfigError(f"{source}: field {name!r} = {getattr(self, name)!r}: {why}")

        if self.shield not in SHIELD_RULES:
            raise bad("shield", f"must be one of {SHIELD_RULES}")
        if self.shield == "lacam":
            raise bad("shield", "the planning arbiter executes its plan, not the policy's moves: "
                                "roll out under 'pibt' or 'pibt_anchor'")
        if self.preferences not in Q_MODES:
            raise bad("preferences", f"must be one of {Q_MODES}")
        if self.loss not in LOSSES:
            raise bad("loss", f"must be one of {LOSSES}")
        if self.observation is not None and self.observation not in OBSERVATIONS:
            raise bad("observation", f"must be one of {OBSERVATIONS} or null (the init "
                      "checkpoint's)")
        for name in ("rounds", "episodes_per_round", "label_interval", "label_backoff_max",
                     "num_cpus", "num_workers",
                     "seq_len", "batch_windows", "threads", "heldout_count"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise bad(name, "must be an integer >= 1")
        for name in ("late_tasks_from", "burn_in", "updates_per_round", "max_plan_slack", "seed",
                     "planner_seed", "heldout_seed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise bad(name, "must be an integer >= 0")
        for name in ("beta0", "beta_decay"):
            if not 0.0 <= float(getattr(self, name)) <= 1.0:
                raise bad(name, "must be in [0, 1]")
        for name in ("label_time_limit", "max_plan_factor", "lr", "grad_clip",
                     "state_interval_seconds"):
            if not float(getattr(self, name)) > 0:
                raise bad(name, "must be > 0")
        if float(self.margin) < 0:
            raise bad("margin", "must be >= 0")
        if self.device not in ("auto", "cpu", "cuda") and not str(self.device).startswith("cuda:"):
            raise bad("device", "must be 'auto', 'cpu', 'cuda' or 'cuda:N'")
        if not self.tasks:
            raise bad("tasks", "needs at least one task")
        for name in ("tasks", "late_tasks"):
            for i, task in enumerate(getattr(self, name)):
                try:
                    _check_task(task, many=True)
                except ValueError as exc:
                    raise bad(name, f"entry {i}: {exc}") from None
        if not self.heldout:
            raise bad("heldout", "needs at least one setting")
        for i, task in enumerate(self.heldout):
            try:
                _check_task(task, many=False)
            except ValueError as exc:
                raise bad("heldout", f"entry {i}: {exc}") from None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def beta(self, round_index: int) -> float:
        return float(self.beta0) * float(self.beta_decay) ** int(round_index)

    def round_tasks(self, round_index: int) -> list[dict]:
        late = self.late_tasks if round_index >= self.late_tasks_from else []
        return list(self.tasks) + list(late)


def _check_task(task: Any, many: bool) -> None:
    from mapf_fleet.grid.maps import GENERATED_KINDS, capacity

    keys = {"kind", "size", "agents", "max_steps"} | ({"weight"} if many else set())
    if not isinstance(task, dict):
        raise ValueError(f"{task!r} is not a mapping with {sorted(keys)}")
    missing, unknown = keys - set(task) - {"weight"}, set(task) - keys
    if missing or unknown:
        raise ValueError(f"{task!r}: missing {sorted(missing)}, unknown {sorted(unknown)}")
    if task["kind"] not in GENERATED_KINDS:
        raise ValueError(f"kind {task['kind']!r} is not one of {GENERATED_KINDS}")
    agents = task["agents"] if many else [task["agents"]]
    if many and (not isinstance(agents, list) or not agents):
        raise ValueError(f"agents {agents!r} must be a non-empty list")
    for name, value in [("size", task["size"]), ("max_steps", task["max_steps"]),
                        *(("agents", a) for a in agents)]:
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} {value!r} must be an integer >= 1")
    room = capacity(task["kind"], task["size"])
    if max(agents) > room:
        raise ValueError(f"{max(agents)} agents do not fit every {task['kind']} map of size "
                         f"{task['size']} (at most {room})")
    weight = task.get("weight", 1.0)
    if isinstance(weight, bool) or not isinstance(weight, (int, float)) or weight < 0:
        raise ValueError(f"weight {weight!r} must be a number >= 0")


def config_from_dict(data: dict, source: str = "<dict>") -> DaggerConfig:
    if not isinstance(data, dict):
        raise DaggerConfigError(f"{source}: top level must be a mapping")
    known = {f.name: f for f in dataclasses.fields(DaggerConfig)}
    values = {}
    for key, value in data.items():
        if key not in known:
            raise DaggerConfigError(f"{source}: unknown field {key!r} (value {value!r})")
        default = known[key].default
        if isinstance(default, float) and isinstance(value, (int, str)) and not isinstance(value, bool):
            try:
                value = float(value)
            except ValueError:
                raise DaggerConfigError(f"{source}: field {key!r} = {value!r}: not a number") from None
        elif isinstance(default, bool) and not isinstance(value, bool):
            raise DaggerConfigError(f"{source}: field {key!r} = {value!r}: must be true/false")
        values[key] = value
    try:
        return DaggerConfig(**values)
    except DaggerConfigError as exc:
        raise DaggerConfigError(str(exc).replace("DaggerConfig:", f"{source}:", 1)) from None
    except TypeError as exc:
        raise DaggerConfigError(f"{source}: {exc}") from None


def load_config(path: str | Path) -> DaggerConfig:
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except OSError as exc:
        raise DaggerConfigError(f"{path}: cannot read DAgger config: {exc}") from exc
    except yaml.YAMLError as exc:
        raise DaggerConfigError(f"{path}: invalid YAML: {exc}") from exc
    return config_from_dict(data, source=str(path))


# -- the expert ------------------------------------------------------------------------------------
class LaCAMLabeller:
    """Every agent's next move from a joint state: the first step of LaCAM's plan to the goals,
    planned per connected free region (agents of different regions never meet). `label`
    returns (actions (N,) int64 with -1 where there is no label, status): status "ok" (every
    agent labelled), "unsolved" (some region got no plan within the limit: its agents have no
    label) or "too_long" (some region's plan exceeded `plan_limit`: its agents have no label)."""

    def __init__(self, time_limit: float, max_plan_factor: float, max_plan_slack: int,
                 seed: int = 0):
        from mapf_fleet.coordination.planners import ClassicalPlanner

        self.planner = ClassicalPlanner("lacam", time_limit, seed)
        self.max_plan_factor = float(max_plan_factor)
        self.max_plan_slack = int(max_plan_slack)

    def plan_limit(self, lower_bound: int, step_limit: int) -> int:
        """The longest plan whose first moves are used (module docstring)."""
        return int(min(step_limit, self.max_plan_factor * lower_bound + self.max_plan_slack))

    def label(self, grid, positions, goals, distances, step_limit: int):
        from mapf_fleet.coordination.planners import positions_to_actions
        from mapf_fleet.grid.instance import free_components

        positions = np.asarray(positions, np.int64)
        goals = np.asarray(goals, np.int64)
        labels = np.full(len(positions), -1, np.int64)
        region = free_components(np.asarray(grid) != 0)[positions[:, 0], positions[:, 1]]
        status = "ok"
        for value in np.unique(region):
            idx = np.flatnonzero(region == value)
            if np.array_equal(positions[idx], goals[idx]):
                labels[idx] = 0  # all on their goals: stay
                continue
            result = self.planner.plan(grid, positions[idx], goals[idx])
            if not result.complete:
                status = "unsolved"
                continue
            lower = int(distances[idx, positions[idx, 0], positions[idx, 1]].max())
            if len(result.positions) - 1 > self.plan_limit(lower, step_limit):
                status = "too_long" if status == "ok" else status
                continue
            labels[idx] = positions_to_actions(result.positions[:2])[0]
        return labels, status


# -- episodes --------------------------------------------------------------------------------------
def window_starts(length: int, seq_len: int, burn_in: int) -> np.ndarray:
    """Step index where window j's unroll begins (its stored hidden state): max(0, j L - B)."""
    return np.maximum(0, np.arange(0, length, seq_len) - burn_in).astype(np.int64)


def play_episode(model, instance, max_steps: int, shield_rule: str, preferences: str,
                 device, labeller: LaCAMLabeller | None = None, beta: float = 0.0,
                 label_interval: int = 1, rng: np.random.Generator | None = None,
                 seq_len: int = 16, burn_in: int = 8, record: bool = True,
                 backoff_max: int = 1) -> dict:
    """One episode of `model` under the shield; with a labeller, the visited states are labelled
    (and the expert's ranking executed with probability `beta` at labelled steps). Returns the
    outcome and, with `record`, the arrays of a shard (see module docstring)."""
    from mapf_fleet.coordination.pibt import make_shield
    from mapf_fleet.coordination.preferences import rank_actions, tie_breakers
    from mapf_fleet.grid.env import EnvConfig, MAPFEnv
    from mapf_fleet.grid.heuristic import bfs_distances_many
    from mapf_fleet.models.policy import LearnedPolicy

    rng = np.random.default_rng(0) if rng is None else rng
    cost_to_go = model.config.observation == "cost_to_go"
    env = MAPFEnv(instance, EnvConfig(max_steps=max_steps, observation=model.config.observation))
    obs = env.reset()
    n = instance.num_agents
    shield = make_shield(shield_rule, instance.grid, instance.goals)
    policy = LearnedPolicy(model, device)
    policy.reset(1, n)
    distances = bfs_distances_many(instance.grid, instance.goals) if labeller else None
    ties_agents = np.arange(n)
    rec_obs, rec_ctg, rec_pos, rec_last, rec_labels, hiddens = [], [], [], [], [], []
    stats = {"labelled_states": 0, "labels": 0, "unsolved": 0, "too_long": 0,
             "expert_steps": 0, "label_seconds": 0.0, "disagree": 0, "disagree_off_goal": 0,
             "off_goal_labels": 0, "label_calls": 0}
    done, info = (env.on_goal().all(), {"success": bool(env.on_goal().all()), "steps": 0})
    next_label, wait = 0, label_interval
    while not done:
        t = env.steps
        if record:
            rec_obs.append(pack_obs(obs))
            if cost_to_go:
                rec_ctg.append(pack_cost_to_go(obs))
            rec_pos.append(env.positions.astype(np.int16))
            rec_last.append(env.last_actions.astype(np.int8))
            hiddens.append(policy.hidden[0].detach().to("cpu", torch.float16).numpy())
        policy.act(obs[None].astype(np.float32), env.positions[None])
        q = policy.q_values[0]
        ties = tie_breakers(ties_agents, t)
        ranking = rank_actions(obs, q, preferences, ties=ties)
        label = np.full(n, -1, np.int8)
        if labeller is not None and t >= next_label:
            began = time.perf_counter()
            expert, status = labeller.label(instance.grid, env.positions, instance.goals,
                                            distances, max_steps)
            stats["label_seconds"] += time.perf_counter() - began
            stats["label_calls"] += 1
            if status != "ok":
                stats[status] += 1
            if 2 * int((expert >= 0).sum()) >= n:  # most agents labelled (a pocket may not be)
                wait = label_interval
            else:  # back off (config: label_backoff_max)
                wait = min(max(wait, label_interval) * 2, max(backoff_max, label_interval))
            next_label = t + wait
            have = expert >= 0
            if have.any():
                label[have] = expert[have]
                stats["labelled_states"] += 1
                stats["labels"] += int(have.sum())
                off_goal = ~env.on_goal() & have
                differ = (ranking[:, 0] != expert) & have
                stats["disagree"] += int(differ.sum())
                stats["disagree_off_goal"] += int((differ & off_goal).sum())
                stats["off_goal_labels"] += int(off_goal.sum())
                if beta > 0 and rng.random() < beta:  # DAgger's mixing: the expert drives
                    # the expert's move first, then the distance order; unlabelled agents
                    # keep the policy's ranking
                    onehot = (np.arange(5) == expert[:, None]).astype(np.float64)
                    ranked = rank_actions(obs, onehot, "q_then_distance", ties=ties)
                    ranking = np.where(have[:, None], ranked, ranking)
                    stats["expert_steps"] += 1
        if record:
            rec_labels.append(label)
        executed = shield.step(env.positions, ranking).actions
        policy.set_last_actions(executed[None])
        obs, _, done, info = env.step(executed)
    out = {"success": bool(info["success"]), "steps": int(info["steps"]),
           "num_agents": n, **stats}
    if record:
        length = len(rec_obs)
        starts = window_starts(length, seq_len, burn_in) if length else np.zeros(0, np.int64)
        hidden = (np.stack([hiddens[s] for s in starts]) if length
                  else np.zeros((0, n, model.config.hidden_dim), np.float16))
        out["arrays"] = {
            "obs_bits": np.stack(rec_obs) if length else np.zeros((0, n, 61), np.uint8),
            "positions": np.stack(rec_pos) if length else np.zeros((0, n, 2), np.int16),
            "last_actions": np.stack(rec_last) if length else np.zeros((0, n), np.int8),
            "labels": np.stack(rec_labels) if length else np.zeros((0, n), np.int8),
            "hidden_starts": starts, "hidden": hidden,
        }
        if cost_to_go:
            fov = obs.shape[-1]
            out["arrays"]["ctg"] = np.stack(rec_ctg) if length else np.zeros((0, n, fov, fov),
                                                                               np.int8)
    return out


def make_instance(task: dict, seed_words: list[int]):
    from mapf_fleet.grid.maps import generate_kind_instance

    return generate_kind_instance(task["kind"], task["size"], task["agents"],
                                  np.random.default_rng(seed_words))


def _kind_code(kind: str) -> int:
    from mapf_fleet.grid.maps import GENERATED_KINDS

    return GENERATED_KINDS.index(kind)


class DaggerWorker:
    """Plays episodes (a Ray actor, or in-process): rollouts with labels, and held-out checks."""

    def __init__(self, cfg: DaggerConfig, model_config: dict):
        from mapf_fleet.models.checkpoint import build_model
        from mapf_fleet.models.config import ModelConfig

        torch.set_num_threads(cfg.threads)
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        self.cfg = cfg
        self.model = build_model(ModelConfig.from_dict(model_config)).eval()
        # inference on the CPU: batch 1, one agent set at a time, the GPU would not pay
        self.device = torch.device("cpu")
        self.labeller = LaCAMLabeller(cfg.label_time_limit, cfg.max_plan_factor,
                                      cfg.max_plan_slack, cfg.planner_seed)
        self.version = None

    def set_weights(self, state_dict: dict, version) -> None:
        self.model.load_state_dict(state_dict)
        self.version = version

    def collect(self, job: dict) -> dict:
        cfg = self.cfg
        instance = make_instance(job["task"], job["seed_words"])
        out = play_episode(self.model, instance, job["task"]["max_steps"], cfg.shield,
                           cfg.preferences, self.device, self.labeller, job["beta"],
                           cfg.label_interval, np.random.default_rng(job["seed_words"] + [1]),
                           cfg.seq_len, cfg.burn_in, record=True,
                           backoff_max=cfg.label_backoff_max)
        return {**out, "job": job, "pid": os.getpid(),
                "process_cpu_seconds": time.process_time()}

    def heldout(self, job: dict) -> dict:
        """One held-out episode; `job["heuristic"]`: plain PIBT (distance ranking, no network)."""
        cfg = self.cfg
        instance = make_instance(job["task"], job["seed_words"])
        if job.get("heuristic"):
            out = play_plain_pibt(instance, job["task"]["max_steps"], cfg.shield)
        else:
            out = play_episode(self.model, instance, job["task"]["max_steps"], cfg.shield,
                               cfg.preferences, self.device, record=False)
        return {**out, "job": job, "pid": os.getpid(),
                "process_cpu_seconds": time.process_time()}


def play_plain_pibt(instance, max_steps: int, shield_rule: str) -> dict:
    """The baseline: the shield over distance rankings (the heuristic checkpoint's rows)."""
    from mapf_fleet.coordination.pibt import make_shield
    from mapf_fleet.coordination.preferences import rank_actions, tie_breakers
    from mapf_fleet.grid.env import EnvConfig, MAPFEnv

    env = MAPFEnv(instance, EnvConfig(max_steps=max_steps))
    obs = env.reset()
    shield = make_shield(shield_rule, instance.grid, instance.goals)
    agents = np.arange(instance.num_agents)
    done, info = bool(env.on_goal().all()), {"success": bool(env.on_goal().all()), "steps": 0}
    while not done:
        ranking = rank_actions(obs, mode="distance", ties=tie_breakers(agents, env.steps))
        obs, _, done, info = env.step(shield.step(env.positions, ranking).actions)
    return {"success": bool(info["success"]), "steps": int(info["steps"]),
            "num_agents": instance.num_agents}


class _LocalWorkers:
    def __init__(self, cfg: DaggerConfig, model_config: dict):
        self.workers = [DaggerWorker(cfg, model_config) for _ in range(cfg.num_workers)]

    def broadcast(self, weights: dict, version) -> None:
        for w in self.workers:
            w.set_weights(weights, version)

    def map(self, method: str, jobs: list[dict]):
        """Yield results as they finish (here: in order)."""
        for k, job in enumerate(jobs):
            yield getattr(self.workers[k % len(self.workers)], method)(job)

    def close(self) -> None:
        pass


class _RayWorkers:
    """Ray actors, like the trainer's: a local Ray on `num_cpus` CPUs, or `ray_address`."""

    def __init__(self, cfg: DaggerConfig, model_config: dict):
        import ray

        from .ray_pool import actor_cpus, init_ray

        self.ray = ray
        self.started = init_ray(cfg.ray_address, cfg.num_cpus)
        cpus = actor_cpus(cfg.ray_address, cfg.num_cpus, cfg.num_workers)
        remote = ray.remote(num_cpus=cpus)(DaggerWorker)
        self.actors = [remote.remote(cfg, model_config) for _ in range(cfg.num_workers)]

    def broadcast(self, weights: dict, version) -> None:
        ref = self.ray.put(weights)
        self.ray.get([a.set_weights.remote(ref, version) for a in self.actors])

    def map(self, method: str, jobs: list[dict]):
        pending, queue, free = {}, list(jobs), list(range(len(self.actors)))
        while queue or pending:
            while queue and free:
                index = free.pop()
                pending[getattr(self.actors[index], method).remote(queue.pop(0))] = index
            ready, _ = self.ray.wait(list(pending), num_returns=1)
            for ref in ready:
                free.append(pending.pop(ref))
                yield self.ray.get(ref)

    def close(self) -> None:
        for actor in self.actors:
            self.ray.kill(actor)
        if self.started:
            self.ray.shutdown()


# -- the data set ------------------------------------------------------------------------------------
def shard_name(round_index: int, episode: int) -> str:
    return f"r{round_index:03d}_e{episode:03d}.npz"


def write_shard(path: Path, arrays: dict, meta: dict) -> None:
    def write(handle):
        np.savez_compressed(handle, **arrays, meta=np.array(json.dumps(meta)))

    atomic_write(path, write)


def read_shard(path: Path) -> tuple[dict, dict]:
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files if k != "meta"}
        meta = json.loads(str(data["meta"]))
    return arrays, meta


def write_json(path: Path, data) -> None:
    atomic_write(path, lambda f: f.write((json.dumps(data, indent=1) + "\n").encode()))


class LabelledData:
    """The aggregate: every shard's arrays in memory, and an index of labelled windows."""

    def __init__(self, seq_len: int, burn_in: int):
        self.seq_len, self.burn_in = seq_len, burn_in
        self.episodes: list[dict] = []
        self.windows: list[tuple[int, int]] = []  # (episode, window j)
        self.names: set[str] = set()

    def add(self, name: str, arrays: dict) -> None:
        if name in self.names:
            return
        self.names.add(name)
        e = len(self.episodes)
        self.episodes.append(arrays)
        labels = arrays["labels"]
        for j in range(len(arrays["hidden_starts"])):
            if (labels[j * self.seq_len:(j + 1) * self.seq_len] >= 0).any():
                self.windows.append((e, j))

    def window(self, e: int, j: int) -> dict:
        """Window j of episode e: steps [start, (j+1) L), the loss on [j L, (j+1) L)."""
        ep = self.episodes[e]
        start = int(ep["hidden_starts"][j])
        end = min(len(ep["labels"]), (j + 1) * self.seq_len)
        ctg = ep["ctg"][start:end] if "ctg" in ep else None
        return {"obs": unpack_obs(ep["obs_bits"][start:end], ctg),
                "positions": ep["positions"][start:end].astype(np.int64),
                "last": ep["last_actions"][start:end].astype(np.int64),
                "labels": ep["labels"][start:end].astype(np.int64),
                "burn": j * self.seq_len - start, "hidden": ep["hidden"][j].astype(np.float32)}


def window_loss(model, algo: str, win: dict, device, loss: str, margin: float):
    """(summed loss over the labelled (step, agent) pairs, their count, agreements): the unroll
    from the stored hidden state, `burn` steps without gradient, then the trained steps."""
    from .demos import cross_entropy_loss, margin_loss

    t = lambda x: torch.as_tensor(x, device=device)  # noqa: E731
    obs, pos, last = t(win["obs"]), t(win["positions"]), t(win["last"])
    h = t(win["hidden"])[None]
    burn = win["burn"]
    with torch.no_grad():
        for s in range(burn):
            h = model_step(model, algo, obs[s][None], pos[s][None], h, last[s][None]).hidden
    qs = []
    for s in range(burn, len(obs)):
        out = model_step(model, algo, obs[s][None], pos[s][None], h, last[s][None])
        h = out.hidden
        qs.append(out.q[0])
    q = torch.stack(qs)  # (L, N, 5)
    labels = t(win["labels"][burn:])
    mask = (labels >= 0).float()
    target = labels.clamp(min=0)
    count = mask.sum()
    if loss == "cross_entropy":
        value = cross_entropy_loss(q, target, mask) * count
    else:
        value = margin_loss(q, target, mask, margin) * count
    agree = ((q.argmax(-1) == target).float() * mask).sum()
    return value, float(count), float(agree)


# -- the driver ------------------------------------------------------------------------------------
class Dagger:
    def __init__(self, cfg: DaggerConfig, run_dir: str | Path, log=print):
        from mapf_fleet.models.checkpoint import load_checkpoint, with_observation

        self.cfg, self.run_dir, self.log = cfg, Path(run_dir), log
        self.run_dir.mkdir(parents=True, exist_ok=True)
        (self.run_dir / DATA_DIR).mkdir(exist_ok=True)
        torch.manual_seed(cfg.seed)
        torch.set_num_threads(cfg.threads)
        self.device = pick_device(cfg.device)
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
        self.data = LabelledData(cfg.seq_len, cfg.burn_in)
        self.stop_signal = None
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
                         "seed_words": [cfg.seed, round_index, e, _kind_code(task["kind"])]})
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
                "rankings": {self.cfg.shield: self.cfg.preferences}}
        return save_checkpoint(self.run_dir / CHECKPOINT_DIR / f"round_{round_index:03d}.pt",
                               self.model, meta)

    def heldout(self, workers, label: str, round_index: int, heuristic: bool = False) -> dict:
        cfg = self.cfg
        jobs = []
        for setting in cfg.heldout:
            for i in range(cfg.heldout_count):
                jobs.append({"task": dict(setting), "heuristic": heuristic,
                             "seed_words": [cfg.heldout_seed, _kind_code(setting["kind"]),
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
        previous = {}

        def handler(signum, _frame):
            self.stop_signal = signal.Signals(signum).name

        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, handler)
        return lambda: [signal.signal(s, h) for s, h in previous.items()]

    def run(self) -> dict:
        cfg = self.cfg
        writer = None
        try:
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(str(self.run_dir / TB_DIR))
        except ImportError:
            self.log("tensorboard not installed: no scalars written")
        self._wall, self._proc = time.monotonic(), time.process_time()
        workers = _RayWorkers(cfg, self.model_config) if cfg.use_ray else \
            _LocalWorkers(cfg, self.model_config)
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


def _read_runs(run_dirs: list[str | Path]) -> list[tuple[Path, dict, list[dict]]]:
    """(run directory, its config, its held-out curve) of each DAgger run directory."""
    runs = []
    for run_dir in map(Path, run_dirs):
        curve_file, config_file = run_dir / CURVE_JSON, run_dir / CONFIG_FILE
        if not curve_file.is_file() or not config_file.is_file():
            raise DaggerConfigError(f"{run_dir}: not a DAgger run directory (no {CURVE_JSON} "
                                    f"or {CONFIG_FILE})")
        runs.append((run_dir, yaml.safe_load(config_file.read_text()) or {},
                     json.loads(curve_file.read_text())))
    return runs


def _heldout_keys(curves) -> list[str]:
    """The held-out settings ("dense21_48", ...) the curves' rows hold, in order of appearance."""
    return list(dict.fromkeys(k[:-len("_success")] for curve in curves for row in curve
                              for k in row if k.endswith("_success")))


def compare_runs(run_dirs: list[str | Path], last: int = 4) -> str:
    """A Markdown table of DAgger runs side by side (the A/Bs of issue 25): per run its loss,
    observation, rounds, labels and CPU-hours, and per held-out setting the success (average
    steps) of plain PIBT, the init checkpoint, the last round, and the mean over the last `last`
    rounds (each round's check is `heldout_count` instances: the mean of several rounds is less
    noisy than any one round, though its rounds are different checkpoints)."""
    if last < 1:
        raise DaggerConfigError(f"--last must be >= 1, got {last}")
    runs = []
    for run_dir, config, curve in _read_runs(run_dirs):
        rounds = sorted((r for r in curve if r["policy"] == "dagger"), key=lambda r: r["round"])
        if not rounds:
            raise DaggerConfigError(f"{run_dir}: no round has finished its held-out check yet")
        runs.append((run_dir, config, curve, rounds))
    keys = _heldout_keys(curve for _, _, curve, _ in runs)

    def cell(rows: list[dict], key: str) -> str:
        have = [r for r in rows if f"{key}_success" in r]
        if not have:
            return ""
        success = float(np.mean([r[f"{key}_success"] for r in have]))
        steps = float(np.mean([r[f"{key}_steps"] for r in have]))
        return f"{success:.2f} ({steps:.0f})"

    lines = ["| run | loss | observation | rounds | labels | CPU-h | policy | "
             + " | ".join(f"{k} success (steps)" for k in keys) + " |",
             "|---|---|---|---:|---:|---:|---|" + "---:|" * len(keys)]
    for run_dir, config, curve, rounds in runs:
        final = rounds[-1]
        base = {r["policy"]: r for r in curve if r["round"] == -1}
        head = (f"| {run_dir.name} | {config.get('loss', '')} | "
                f"{config.get('observation') or 'init'} | {final['round'] + 1} | "
                f"{final['labels']:,} | {final['cpu_seconds'] / 3600:.2f} |")
        blank = "| | | | | | |"
        table = [("plain PIBT", [base["plain_pibt"]] if "plain_pibt" in base else []),
                 ("init", [base["init"]] if "init" in base else []),
                 (f"round {final['round']}", [final]),
                 (f"mean of rounds {rounds[-last:][0]['round']}-{final['round']}", rounds[-last:])]
        for i, (label, rows) in enumerate(table):
            lines.append(f"{head if i == 0 else blank} {label} | "
                         + " | ".join(cell(rows, k) for k in keys) + " |")
    return "\n".join(lines)


def plot_runs(run_dirs: list[str | Path], out: str | Path) -> Path:
    """The DAgger curves as a PNG: per held-out setting, each run's success per round (the init
    checkpoint at round -1) and plain PIBT's as a dashed line (the first run's)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = [(run_dir.name, curve) for run_dir, _, curve in _read_runs(run_dirs)]
    keys = _heldout_keys(curve for _, curve in curves)
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.4), squeeze=False)
    for ax, key in zip(axes[0], keys):
        for name, curve in curves:
            rows = sorted((r for r in curve if r["policy"] in ("init", "dagger")
                           and f"{key}_success" in r), key=lambda r: r["round"])
            ax.plot([r["round"] for r in rows], [r[f"{key}_success"] for r in rows],
                    marker="o", ms=3, label=name)
        base = [r for r in curves[0][1] if r["policy"] == "plain_pibt" and f"{key}_success" in r]
        if base:
            ax.axhline(base[0][f"{key}_success"], color="k", ls="--", lw=1, label="plain PIBT")
        ax.set_title(key)
        ax.set_xlabel("round (-1: init)")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("held-out success")
    axes[0][-1].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    out = Path(out)
    atomic_write(out, lambda f: fig.savefig(f, format="png", dpi=110))
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    import argparse
    import sys

    parser = argparse.ArgumentParser(prog="mapf-fleet dagger", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", help="DAgger config YAML (config/training/dagger_*.yaml); "
                                         "ignored when RUN already holds a run (it resumes)")
    parser.add_argument("--run-dir", help="run directory (created; rerun to resume)")
    parser.add_argument("--compare", nargs="+", metavar="RUN",
                        help="print a Markdown table of these runs' held-out curves side by side "
                             "(the A/Bs) and exit; no training")
    parser.add_argument("--last", type=int, default=4,
                        help="with --compare: average the held-out checks of the last K rounds")
    parser.add_argument("--plot", metavar="PNG",
                        help="with --compare: also draw the runs' success per round to this PNG")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="override a config field (repeatable; also on a resume)")
    args = parser.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if args.compare:
        try:
            print(compare_runs(args.compare, args.last))
            if args.plot:
                print(f"curves: {plot_runs(args.compare, args.plot)}")
        except (DaggerConfigError, OSError, ValueError, KeyError) as exc:
            print(f"mapf-fleet dagger: {exc}", file=sys.stderr)
            return 2
        return 0
    if not args.run_dir:
        parser.error("--run-dir is required (or --compare RUN ...)")
    run_dir = Path(args.run_dir)
    try:
        overrides = {}
        for item in args.set:
            if "=" not in item:
                raise DaggerConfigError(f"--set expects FIELD=VALUE, got {item!r}")
            key, value = item.split("=", 1)
            overrides[key.strip()] = yaml.safe_load(value)
        if (run_dir / STATE_JSON).is_file():
            data = yaml.safe_load((run_dir / CONFIG_FILE).read_text()) or {}
            source = str(run_dir / CONFIG_FILE)
        elif args.config:
            data = yaml.safe_load(Path(args.config).read_text()) or {}
            source = args.config
        else:
            raise DaggerConfigError(f"{run_dir}: no run to resume; give --config")
        cfg = config_from_dict({**data, **overrides}, source=source)
        result = Dagger(cfg, run_dir, log=lambda m: print(m, flush=True)).run()
    except (DaggerConfigError, FileNotFoundError, OSError) as exc:
        print(f"mapf-fleet dagger: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result, indent=1))
    return 0
