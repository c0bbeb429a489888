"""`TrainConfig`: every knob of the trainer in one validated dataclass.

Defaults are the paper's DHC values (appendix Table 3); `DCC_PAPER_OVERRIDES` holds the DCC column.
YAML files in `config/training/` may set any field; unknown fields and bad values raise
`TrainConfigError` naming the file, the field and the value.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mapf_fleet.aliases import renamed_keys


class TrainConfigError(ValueError):
    """A training configuration value is missing, unknown or out of range."""


@dataclass
class TrainConfig:
    # --- algorithm and network -------------------------------------------------------------
    algo: str = "dhc"  # "dhc" | "dcc"
    model_preset: str = "paper"  # name of a mapf_fleet.models.config preset ("paper" | "small")
    model_overrides: dict = field(default_factory=dict)  # extra ModelConfig fields

    # --- Ape-X actors (Ray) ----------------------------------------------------------------
    ray_address: str | None = None  # join this Ray cluster; None starts a local Ray
    num_cpus: int = 2  # CPUs of the local Ray (ignored when ray_address is given)
    use_ray: bool = True  # False runs the actors in-process (tests, debugging)
    num_actors: int = 16
    envs_per_actor: int = 1  # environments stepped together (batched inference) per actor
    actor_steps_per_call: int = 64  # batched env steps an actor plays per remote call
    epsilon_base: float = 0.4  # explorer i explores with base^(1 + exp * i / (N - 1))
    epsilon_exponent: float = 7.0
    # True: every environment slot of every actor is its own Ape-X explorer (N = num_actors x
    # envs_per_actor epsilons), so even one or two actors cover the whole schedule; False: one
    # epsilon per actor (the paper, where each actor runs one environment).
    epsilon_per_env: bool = True
    # False (the reference's Ape-X scheme): epsilon on agent 0 only; every agent is still trained.
    # True: every agent epsilon-greedy. Why not: with every agent exploring, waiting beside a
    # neighbour pays in training (exploring neighbours step aside at random) and the greedy
    # policy deadlocks at test time (docs/results.md, "What do the shipped checkpoints score on
    # the paper's protocol": the snapshots with every agent exploring).
    explore_all_agents: bool = False
    # conflict_rule "pibt": actors act through the coordination layer (mapf_fleet.coordination.pibt): each
    # agent's ranking (`ranking` over its Q-values; an exploring agent's random action
    # ranked first) is arbitrated by PIBT, the environment executes the result, and the replay
    # stores the EXECUTED action, so the learner trains Q on what really happened (and DCC's
    # last-action input is the executed action, as at test time). "revert": the paper's recipe.
    # "pibt_anchor": the same with the top-priority agent on its distance order
    # (`PIBTShield(anchor=True)`, the fleet's `--conflict-rule pibt_anchor`).
    conflict_rule: str = "revert"
    ranking: str = "q"
    # the guidance graph the observations' heuristic channels and the conflict rule read
    # (grid.guidance_made.GuidanceSource: none, highways, a guidance file, a cost model)
    guidance: str = "none"
    # Under a coordinated conflict rule ("pibt", ...), which action the replay trains Q on.
    # "executed" (above): Q of the move PIBT let happen; a first choice PIBT overrode is never
    # trained, so a policy that keeps asking for blocked moves is never told (it did not beat
    # "revert": docs/results.md).
    # "preferred": each agent's own first choice (its greedy or exploring action), with the
    # reward and next observation of what the shield made of it: the shield is part of the
    # environment, as it is at deployment, and Q(s, a) learns what asking for `a` under PIBT
    # returns. DCC's last-action input stays the executed action in both.
    replay_action: str = "executed"
    actor_update_interval: int = 400  # learner updates between weight broadcasts
    gate_actor_fraction: float = 0.5  # success gate uses the lowest-epsilon fraction of explorers

    # --- environment -------------------------------------------------------------------------
    max_episode_steps: int = 256
    # > 0: the step limit of a curriculum task is min(max_episode_steps, ceil(f * map side)), so
    # 6.4 gives the paper's 256 at 40x40 but 64 at 10x10, where a looping policy would otherwise
    # fill the replay with 256-step failures of a task solved in about 7 steps. 0: always
    # max_episode_steps (reference).
    max_steps_per_map_side: float = 0.0
    obstacle_density: str | float = "triangular"  # "triangular" (0, .33, .5) or a fixed value
    finish_reward: str = "team"  # "team" (reference) | "per_agent"

    # --- learner -----------------------------------------------------------------------------
    batch_size: int = 192  # sequences per learner update
    seq_len: int = 16  # trained steps per sequence
    burn_in: int = 0  # steps replayed from the stored hidden state without a loss
    n_step: int = 2
    gamma: float = 0.99
    lr: float = 1e-4
    grad_clip: float = 40.0
    target_update_interval: int = 2000
    learning_starts: int = 50_000  # agent-0 transitions (env steps) in replay before learning
    max_updates: int = 600_000  # hard cap on learner updates over the whole run
    huber_delta: float = 1.0
    learner_threads: int = 1  # torch threads of the learner (CPU)
    device: str = "auto"  # "auto" = cuda when present, else cpu
    updates_per_poll: int = 1  # learner updates between polls of the actors
    # Sequences sampled per sequence added to the replay, at most (0 = no limit, Ape-X's
    # learner runs flat out). Why: on a few CPU cores a small task's learner outruns its actors
    # and reuses each sample many times, and fine-tuning at 40x40 density collapsed at a high
    # ratio (docs/results.md, "Training at the evaluation's density"). With a limit the learner
    # waits for the actors.
    max_replay_ratio: float = 0.0

    # --- replay -------------------------------------------------------------------------------
    replay_capacity: int = 2048 * 16  # sequences (paper: 2048 episodes of up to 16 sequences)
    priority_alpha: float = 0.6
    priority_beta: float = 0.4
    priority_eta: float = 0.9  # sequence priority = eta * max|td| + (1 - eta) * mean|td| (R2D2)
    priority_epsilon: float = 1e-6

    # A checkpoint file whose weights start the run (online and target network), e.g. to
    # continue a shipped policy on crowded tasks; its algorithm and network configuration must
    # be this config's. "" = random initialisation (the paper).
    init_checkpoint: str = ""

    # --- demonstration warm start (DQfD-style, mapf_fleet.training.demos), off by default ---
    demo_source: str = "none"  # "none" | "heuristic" (non-learned policy) | "planner" (LaCAM)
    demo_episodes: int = 200  # demonstration episodes, spread over the stage-1 settings
    demo_max_agents: int = 0  # demos use stage-1 settings up to this many agents (0 = all)
    demo_pretrain_updates: int = 1000  # learner updates on demonstrations before stage 1
    demo_margin: float = 0.8  # large margin of J_E (DQfD)
    demo_weight: float = 1.0  # lambda: loss = n-step TD + demo_weight * J_E
    # The warm start's loss: "margin" = DQfD, n-step TD plus
    # demo_weight x the large-margin loss J_E; "cross_entropy" = behaviour cloning, demo_weight
    # x the cross-entropy of the demonstrator's action under softmax(Q) and no TD term (the
    # outputs become action logits; their order is what the PIBT shield's ranking reads).
    demo_loss: str = "margin"
    # Explicit [agents, map size] pairs to draw demonstrations from (cycled), e.g. the
    # evaluation's 40x40 maps; empty = the stage-1 ladder up to demo_max_agents. Agents must be
    # <= final_agents (the replay's width).
    demo_settings: list = field(default_factory=list)
    # > 0: keep the demonstrations after the warm start and make every n-th learner update of
    # the curricula a demonstration update (TD + margin loss), as DQfD keeps its demo data.
    demo_interleave: int = 0

    # --- training mix over map kinds (mapf_fleet.grid.maps.TaskMix) ---------------------------
    # {} = unused (the curriculum's random maps). Otherwise {kinds: {random|maze|rooms|warehouse:
    # weight}, sizes: [map sides], agents: [agent counts]}, every count fitting every kind and
    # size and at most final_agents (the replay's width). Every actor episode, in both stages,
    # is then drawn with `mapf_fleet.grid.maps.sample_task_instance(mix, rng)` (kind by weight,
    # side and agent count uniformly; "random" maps at the training triangular density, whatever
    # obstacle_density says), with the step limit `episode_step_limit` of the drawn side. The
    # gates are unchanged but measured on mix tasks: stage 1 has no ladder (the mix defines the
    # tasks), it is one pass of the success gate at alpha 0, after which the run moves to the
    # final setting and stage 2 (the alpha curriculum) runs on mix tasks too. As without a mix,
    # start_agents = final_agents and start_map_size = final_map_size skip stage 1; the other
    # stage-1 fields (map_size_step, final_map_size) choose nothing then. Demonstrations
    # (demo_source) still use their own settings (demo_settings or the stage-1 ladder).
    task_mix: dict = field(default_factory=dict)

    # --- stage 1: scale expansion -----------------------------------------------------------
    start_agents: int = 1
    start_map_size: int = 10
    final_agents: int = 12
    final_map_size: int = 40
    map_size_step: int = 5
    success_window: int = 200
    success_threshold: float = 0.9

    # --- stage 2: cooperative exploration ---------------------------------------------------
    alpha_mode: str = "curriculum"  # "curriculum" | "fixed" (the paper's "w/o CL") | "none"
    fixed_alpha: float = 0.3
    alpha_step: float = 0.1
    alpha_max: float = 1.0
    # "converged without reaching the threshold" (Algorithm 1, line 19): the alpha fails when
    # either budget below runs out first. 0 disables a rule; at least one must be on.
    alpha_max_updates: int = 100_000  # learner updates allowed per alpha
    # Learner updates at each alpha before its gate window starts counting (0 = the paper's rule
    # as written: the window opens at once). Why: where 200 gate episodes take only a few dozen
    # learner updates (small final tasks on CPU), the window right after a step measures the
    # previous alpha's policy, so every alpha "passes" before it has changed anything.
    alpha_min_updates: int = 0
    plateau_windows: int = 10  # K consecutive full 200-episode windows without a new best ...
    plateau_min_delta: float = 0.01  # ... success rate by more than this

    # --- run directory --------------------------------------------------------------------------
    state_interval_updates: int = 500  # training state saved at least every N updates ...
    state_interval_seconds: float = 300.0  # ... and every this many seconds
    # the replay (RUN/replay.npz, ~170 MB at 8192 x 24 steps x 12 agents) is saved when the run
    # stops and every this many seconds (0: only when it stops); a resume reloads it
    replay_interval_seconds: float = 1800.0
    log_interval_seconds: float = 10.0
    max_wall_seconds: float = 0.0  # stop (saving state) after this long; 0 = no limit
    seed: int = 0
    progress_bar: bool = True

    def __post_init__(self) -> None:
        self.validate()

    # ------------------------------------------------------------------------------------------
    def validate(self, source: str = "TrainConfig") -> None:
        def bad(name: str, why: str) -> TrainConfigError:
            return TrainConfigError(f"{source}: field {name!r} = {getattr(self, name)!r}: {why}")

        if self.algo not in ("dhc", "dcc"):
            raise bad("algo", "must be 'dhc' or 'dcc'")
        if self.alpha_mode not in ("curriculum", "fixed", "none"):
            raise bad("alpha_mode", "must be 'curriculum', 'fixed' or 'none'")
        if self.demo_source not in ("none", "heuristic", "planner"):
            raise bad("demo_source", "must be 'none', 'heuristic' or 'planner'")
        if self.demo_loss not in ("margin", "cross_entropy"):
            raise bad("demo_loss", "must be 'margin' (DQfD) or 'cross_entropy' (behaviour cloning)")
        for name in ("demo_margin", "demo_weight"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
                raise bad(name, "must be a number >= 0")
        if self.finish_reward not in ("team", "per_agent"):
            raise bad("finish_reward", "must be 'team' or 'per_agent'")
        from mapf_fleet.coordination.rules import Rule

        try:
            rule = Rule.parse(self.conflict_rule)
        except ValueError as exc:
            raise bad("conflict_rule", str(exc)) from None
        from mapf_fleet.grid.guidance_made import GuidanceSource

        try:
            GuidanceSource.parse(self.guidance)
        except ValueError as exc:
            raise bad("guidance", str(exc)) from None
        if rule.is_lacam:
            raise bad("conflict_rule", "the planning arbiter executes its plan, not the "
                                       "policy's moves: train under 'pibt' or 'pibt_anchor'")
        if self.replay_action not in ("executed", "preferred"):
            raise bad("replay_action", "must be 'executed' or 'preferred'")
        from mapf_fleet.coordination.ranking import Q_RANKINGS

        if self.ranking not in Q_RANKINGS:
            raise bad("ranking", f"must be one of {Q_RANKINGS}")
        if isinstance(self.obstacle_density, str):
            if self.obstacle_density != "triangular":
                raise bad("obstacle_density", "must be 'triangular' or a number in [0, 0.9]")
        elif not 0.0 <= float(self.obstacle_density) <= 0.9:
            raise bad("obstacle_density", "must be 'triangular' or a number in [0, 0.9]")
        positive = ["num_cpus", "envs_per_actor", "actor_steps_per_call", "actor_update_interval",
                    "max_episode_steps", "batch_size", "seq_len", "n_step",
                    "target_update_interval", "max_updates", "learner_threads", "updates_per_poll",
                    "replay_capacity", "start_agents", "start_map_size", "final_agents",
                    "final_map_size", "success_window", "state_interval_updates"]
        for name in positive:
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
                raise bad(name, "must be an integer >= 1")
        non_negative = ["num_actors", "burn_in", "learning_starts", "map_size_step",
                        "demo_episodes", "demo_max_agents", "demo_pretrain_updates",
                        "demo_interleave",
                        "alpha_max_updates", "alpha_min_updates", "plateau_windows", "seed"]
        for name in non_negative:
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 0:
                raise bad(name, "must be an integer >= 0")
        if self.num_actors < 1:
            raise bad("num_actors", "need at least one actor")
        unit = ["epsilon_base", "gamma", "priority_alpha", "priority_beta", "priority_eta",
                "success_threshold", "gate_actor_fraction", "fixed_alpha", "alpha_max"]
        for name in unit:
            if not 0.0 <= float(getattr(self, name)) <= 1.0:
                raise bad(name, "must be in [0, 1]")
        if self.gate_actor_fraction <= 0:
            raise bad("gate_actor_fraction", "must be > 0")
        for name in ["lr", "grad_clip", "huber_delta", "alpha_step", "priority_epsilon",
                     "state_interval_seconds", "log_interval_seconds"]:
            if not float(getattr(self, name)) > 0:
                raise bad(name, "must be > 0")
        if self.max_wall_seconds < 0:
            raise bad("max_wall_seconds", "must be >= 0 (0 = no limit)")
        if not float(self.max_replay_ratio) >= 0:
            raise bad("max_replay_ratio", "must be >= 0 (0 = no limit)")
        if self.replay_interval_seconds < 0:
            raise bad("replay_interval_seconds", "must be >= 0 (0 = only when the run stops)")
        if self.demo_source != "none" and (self.demo_episodes < 1
                                            or self.demo_pretrain_updates < 1):
            raise bad("demo_source", "needs demo_episodes >= 1 and demo_pretrain_updates >= 1")
        if not isinstance(self.demo_settings, list):
            raise bad("demo_settings", "must be a list of [agents, map size] pairs")
        for pair in self.demo_settings:
            if (not isinstance(pair, (list, tuple)) or len(pair) != 2
                    or not all(isinstance(v, int) and not isinstance(v, bool) for v in pair)):
                raise bad("demo_settings", f"entry {pair!r} is not an [agents, map size] pair")
            if not 1 <= pair[0] <= self.final_agents:
                raise bad("demo_settings", f"entry {pair!r}: agents must be in 1..final_agents "
                          f"({self.final_agents})")
            if pair[1] < 5:
                raise bad("demo_settings", f"entry {pair!r}: map size must be >= 5")
        if self.demo_interleave and self.demo_source == "none":
            raise bad("demo_interleave", "needs a demo_source")
        if self.max_steps_per_map_side < 0:
            raise bad("max_steps_per_map_side", "must be >= 0 (0 = max_episode_steps always)")
        if self.epsilon_exponent < 0:
            raise bad("epsilon_exponent", "must be >= 0")
        if self.final_agents < self.start_agents:
            raise bad("final_agents", f"must be >= start_agents ({self.start_agents})")
        if self.final_map_size < self.start_map_size:
            raise bad("final_map_size", f"must be >= start_map_size ({self.start_map_size})")
        if self.alpha_max_updates == 0 and self.plateau_windows == 0:
            raise bad("alpha_max_updates", "and plateau_windows are both 0: an alpha that never "
                      "passes the gate would train forever; enable at least one stop rule")
        if self.alpha_max_updates and self.alpha_min_updates >= self.alpha_max_updates:
            raise bad("alpha_min_updates", f"must be below alpha_max_updates "
                      f"({self.alpha_max_updates}): no alpha could pass its gate")
        if self.device not in ("auto", "cpu", "cuda") and not self.device.startswith("cuda:"):
            raise bad("device", "must be 'auto', 'cpu', 'cuda' or 'cuda:N'")
        if not isinstance(self.model_overrides, dict):
            raise bad("model_overrides", "must be a mapping")
        if self.model_overrides.get("observation", "paper") != "paper":
            # the actors' replay bit-packs the paper's six binary channels only
            raise bad("model_overrides", "the Ape-X trainer builds the paper's observation "
                      "only; train a cost_to_go network with `mapf-fleet dagger --set "
                      "observation=cost_to_go`")
        if not isinstance(self.task_mix, dict):
            raise bad("task_mix", "must be a mapping (kinds, sizes, agents), or {} for none")
        if self.task_mix:
            from mapf_fleet.grid.maps import TaskMix

            try:
                mix = TaskMix.from_dict(self.task_mix)
            except ValueError as exc:
                raise bad("task_mix", str(exc)) from None
            if max(mix.agents) > self.final_agents:
                raise bad("task_mix", f"agents: {max(mix.agents)} agents exceed final_agents "
                          f"({self.final_agents}), the replay's width; raise final_agents")

    # ------------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def replace(self, **changes: Any) -> "TrainConfig":
        """A copy with `changes`, checked like a YAML file's fields (types included)."""
        return config_from_dict({**self.to_dict(), **changes}, source="TrainConfig.replace")

    @property
    def window_len(self) -> int:
        """Observation steps stored per replay sequence: burn-in + trained steps + bootstrap."""
        return self.burn_in + self.seq_len + self.n_step

    def actor_epsilon(self, index: int) -> float:
        """Ape-X schedule epsilon_i = base^(1 + exp * i / (N - 1)); a single actor takes the
        middle of the schedule (i / (N - 1) := 0.5) so it neither explores at 0.4 nor never."""
        n = self.num_actors
        frac = 0.5 if n == 1 else index / (n - 1)
        return float(self.epsilon_base ** (1.0 + self.epsilon_exponent * frac))

    def gate_actor_indices(self) -> list[int]:
        """The lowest-epsilon actors whose episodes drive the curricula (at least one)."""
        count = max(1, int(round(self.num_actors * self.gate_actor_fraction)))
        return list(range(self.num_actors - count, self.num_actors))

    # -- exploration slots --------------------------------------------------------------------
    @property
    def num_explorers(self) -> int:
        return self.num_actors * self.envs_per_actor if self.epsilon_per_env else self.num_actors

    def explorer_index(self, actor: int, env_slot: int) -> int:
        """Position of (actor, env slot) in the epsilon schedule. Interleaved (slot-major) so
        that every actor holds a spread of epsilons, from exploring to nearly greedy."""
        if not self.epsilon_per_env:
            return actor
        return env_slot * self.num_actors + actor

    def _schedule(self, index: int, count: int) -> float:
        frac = 0.5 if count == 1 else index / (count - 1)
        return float(self.epsilon_base ** (1.0 + self.epsilon_exponent * frac))

    def slot_epsilon(self, actor: int, env_slot: int) -> float:
        return self._schedule(self.explorer_index(actor, env_slot), self.num_explorers)

    def is_gate_slot(self, actor: int, env_slot: int) -> bool:
        """Episodes of the lowest-epsilon `gate_actor_fraction` of explorers drive the gates."""
        count = max(1, int(round(self.num_explorers * self.gate_actor_fraction)))
        return self.explorer_index(actor, env_slot) >= self.num_explorers - count

    def episode_step_limit(self, map_size: int) -> int:
        if self.max_steps_per_map_side <= 0:
            return self.max_episode_steps
        return int(min(self.max_episode_steps, math.ceil(self.max_steps_per_map_side * map_size)))


# The DCC column of Table 3 (and the DCC reference's learning rate).
DCC_PAPER_OVERRIDES: dict[str, Any] = {
    "algo": "dcc",
    "batch_size": 128,
    "seq_len": 20,
    "burn_in": 20,
    "lr": 2e-4,
    "target_update_interval": 1750,
    "max_updates": 150_000,
    "actor_update_interval": 200,
    "final_agents": 16,
    "replay_capacity": 262_144 // 20,  # 262144 transitions in sequences of 20
}

PRESETS: dict[str, dict[str, Any]] = {"dhc": {}, "dcc": DCC_PAPER_OVERRIDES}


def config_from_dict(data: dict[str, Any], source: str = "<dict>", quiet: bool = False) -> TrainConfig:
    """Build a config from a mapping. A `preset: dhc|dcc` key starts from that column of the
    paper's table; other keys override it. The deprecated keys (`shield`, `shield_preferences`)
    are read as their new names (`mapf_fleet.aliases`), with a warning unless `quiet` (a
    checkpoint's recorded config)."""
    if not isinstance(data, dict):
        raise TrainConfigError(f"{source}: top level must be a mapping, got {type(data).__name__}")
    try:
        data = renamed_keys(data, source, quiet)
    except ValueError as exc:
        raise TrainConfigError(str(exc)) from None
    preset = data.pop("preset", None)
    values: dict[str, Any] = {}
    if preset is not None:
        if preset not in PRESETS:
            raise TrainConfigError(f"{source}: field 'preset' = {preset!r}: must be one of "
                                   f"{sorted(PRESETS)}")
        values.update(PRESETS[preset])
    known = {f.name: f for f in dataclasses.fields(TrainConfig)}
    for key, value in data.items():
        if key not in known:
            raise TrainConfigError(f"{source}: unknown field {key!r} (value {value!r})")
        values[key] = value
    # YAML writes 1e-4 as a string unless it has a dot; coerce numbers by the default's type.
    for key, value in list(values.items()):
        default = known[key].default
        if isinstance(default, float) and isinstance(value, (int, str)) and not isinstance(value, bool):
            try:
                values[key] = float(value)
            except ValueError as exc:
                raise TrainConfigError(f"{source}: field {key!r} = {value!r}: not a number") from exc
        elif isinstance(default, bool) and not isinstance(value, bool):
            raise TrainConfigError(f"{source}: field {key!r} = {value!r}: must be true/false")
        elif isinstance(default, int) and not isinstance(default, bool):
            if isinstance(value, float) and value.is_integer():
                values[key] = int(value)
            elif isinstance(value, bool) or not isinstance(value, int):
                raise TrainConfigError(f"{source}: field {key!r} = {value!r}: must be an integer")
    try:
        config = TrainConfig(**values)
    except TrainConfigError as exc:
        raise TrainConfigError(str(exc).replace("TrainConfig:", f"{source}:", 1)) from None
    return config


def load_config(path: str | Path) -> TrainConfig:
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise TrainConfigError(f"{path}: cannot read training config: {exc}") from exc
    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise TrainConfigError(f"{path}: invalid YAML: {exc}") from exc
    return config_from_dict(data, source=str(path))


def save_config(config: TrainConfig, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(config.to_dict(), sort_keys=False))
