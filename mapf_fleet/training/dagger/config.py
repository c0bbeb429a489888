"""DAgger's configuration: `DaggerConfig`, its checks and its YAML loader (one clear line per bad
field, naming the file, the field and the value)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mapf_fleet.aliases import renamed_keys

LOSSES = ("cross_entropy", "margin")
COMMITTED_PLANNERS = ("lacam", "pymapf")


class DaggerConfigError(ValueError):
    """A DAgger configuration value is missing, unknown or out of range."""


def _default_tasks() -> list:
    return [
        # where the shipped default fails (docs/results.md): small crowded random maps, 128 steps
        {"kind": "dense", "size": 21, "agents": [32, 48, 64], "weight": 3.0, "max_steps": 128},
        {"kind": "random", "size": 40, "agents": [16, 32, 64], "weight": 2.0, "max_steps": 256},
        {"kind": "maze", "size": 40, "agents": [16, 32], "weight": 1.0, "max_steps": 256},
        {"kind": "rooms", "size": 40, "agents": [32, 64], "weight": 1.0, "max_steps": 256},
        {"kind": "warehouse", "size": 40, "agents": [32, 64], "weight": 1.0, "max_steps": 256},
    ]


def _default_late_tasks() -> list:
    return [{"kind": "random", "size": 80, "agents": [64], "weight": 1.0, "max_steps": 386}]


def _default_ceiling() -> list:
    # the expert-ceiling's suites: where plain PIBT and the shipped default fail (docs/results.md,
    # "The expert ceiling")
    return [{"kind": "dense", "size": 21, "agents": [32, 48, 64], "max_steps": 128},
            {"kind": "maze", "size": 21, "agents": [32, 48], "max_steps": 128},
            {"kind": "random", "size": 40, "agents": [64], "max_steps": 256}]


def _default_ceiling_lifelong() -> list:
    return [{"kind": "dense", "size": 21, "agents": [48], "max_steps": 256}]


def _default_heldout() -> list:
    return [{"kind": "dense", "size": 21, "agents": 48, "max_steps": 128},
            {"kind": "random", "size": 40, "agents": 64, "max_steps": 256}]


@dataclass
class DaggerConfig:
    # --- policy ------------------------------------------------------------------------------
    # the checkpoint DAgger starts from (its network is kept: DCC or DHC as the paper built it)
    init_checkpoint: str = "models/default.pt"
    conflict_rule: str = "pibt_anchor"  # the arbiter the rollouts run under (coordination.rules)
    # the guidance graph the rollouts' observations and rule read (GuidanceSource spelling);
    # the labellers' planners plan unguided
    guidance: str = "none"
    # the anchor's patience (ticks the top agent may go without getting closer before the anchor
    # ranks it by distance; coordination.pibt.PIBTShield): None = the rule's (0, every tick, for
    # `pibt_anchor...`; ANCHOR_PATIENCE for `pibt_patient...`)
    anchor_patience: int | None = None
    # how the policy's Q-values become the ranking the rule reads (coordination.ranking);
    # q_then_distance: the best ranking under pibt_anchor (docs/results.md, "Ranking modes under
    # the anchored shield")
    ranking: str = "q_then_distance"
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
    # half the agents), the next label waits twice as long as the last wait, up to this many
    # steps; a labelled state resets it (1 = never wait). Why: a deadlocked crowd stays
    # unsolvable for LaCAM for many steps, each call spending the whole time limit
    # (docs/results.md, "DAgger behind the arbiter").
    label_backoff_max: int = 16

    # --- expert --------------------------------------------------------------------------------
    # the label scheme (labeller.LABELLERS): "lacam" = a fresh LaCAM plan's first move at every
    # labelled state; "committed" = the next move of one kept plan, re-planned only when the
    # state left it, a goal changed, or every `committed_replan_every` states; "stuck" = the
    # committed expert from the state where the rollout stopped progressing
    labeller: str = "lacam"
    committed_budget: float = 1.0  # "committed": seconds of wall clock per re-plan
    committed_replan_every: int = 0  # "committed": re-plan every k labelled states (0: never)
    # "committed": whose LaCAM keeps the plan: "lacam" = the project's (coordination.lacam, via
    # coordination.plan.CommittedExpert); "pymapf" = the per-step labeller's (no periodic
    # re-plan; `committed_budget` seconds per region)
    committed_planner: str = "lacam"
    # "committed" / "stuck" over the project's LaCAM: successors by PIBT with swap (lacam3's;
    # it lifts the expert's ceiling above plain PIBT under `pibt_anchor_swap`, docs/results.md,
    # "The expert ceiling, second reading")
    committed_swap: bool = False
    # ... and LaCAM's node budget per re-plan: with a generous `committed_budget` the labels
    # then do not depend on the machine's load
    committed_max_nodes: int = 1_000_000
    # ... and labels that the rollout's rule (`conflict_rule`) lets through: the expert asks a
    # copy of the rule what it would execute and re-plans from the rule's priorities and its
    # anchored top agent where that leaves the plan (coordination.plan.CommittedExpert)
    committed_follow_rule: bool = False
    # ... and LaCAM searches per re-plan (tie-breaking seeds planner_seed, +1, ...), the shortest
    # plan kept (coordination.plan.PlanKeeper's `restarts`)
    committed_restarts: int = 1
    # "stuck": the committed expert's labels from the first state after `stuck_window` labelled
    # states without a new low of the agents' summed distance to their goals
    stuck_window: int = 8
    label_time_limit: float = 0.5  # "lacam": seconds of LaCAM per connected region
    max_plan_factor: float = 3.0  # a plan longer than factor x BFS lower bound + slack ...
    max_plan_slack: int = 32  # ... (or than the task's step limit) gives no labels
    planner_seed: int = 0

    # --- workers -------------------------------------------------------------------------------
    use_ray: bool = True  # False: episodes play in the driver process
    ray_address: str | None = None  # join this Ray cluster; None starts a local Ray
    num_cpus: int = 1  # CPUs of the local Ray
    num_workers: int = 1

    # --- learner -------------------------------------------------------------------------------
    # "margin" (DQfD) | "cross_entropy"; margin won the loss A/B at matched compute
    # (docs/results.md, "DAgger behind the arbiter")
    loss: str = "margin"
    margin: float = 0.8  # the large margin of loss "margin"
    # the largest fraction of wait labels trained on per episode (data.cap_wait_labels; the
    # shards keep every label); 1.0 = no cap, MAPF-GPT's is 0.2
    wait_label_cap: float = 1.0
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

    # --- expert ceiling (`mapf-fleet dagger --expert-ceiling`, ceiling.py) ---------------------
    # one-shot suites {kind, size, agents: [..], max_steps}: the labeller as the policy beside
    # plain PIBT, `ceiling_count` instances each from `ceiling_seed`
    ceiling: list = field(default_factory=_default_ceiling)
    ceiling_lifelong: list = field(default_factory=_default_ceiling_lifelong)  # [] = none
    ceiling_count: int = 20
    ceiling_lifelong_count: int = 5  # lifelong runs per row (a goal on arrival: many re-plans)
    ceiling_seed: int = 0
    # episodes per suite whose states a second labeller (planner seed + 1) labels too
    ceiling_agreement_episodes: int = 5

    # --- run -------------------------------------------------------------------------------------
    seed: int = 0
    state_interval_seconds: float = 120.0

    def __post_init__(self) -> None:
        self.validate()

    def validate(self, source: str = "DaggerConfig") -> None:
        from mapf_fleet.coordination.rules import Rule
        from mapf_fleet.coordination.ranking import Q_RANKINGS
        from mapf_fleet.grid.env import OBSERVATIONS

        def bad(name: str, why: str) -> DaggerConfigError:
            return DaggerConfigError(f"{source}: field {name!r} = {getattr(self, name)!r}: {why}")

        try:
            rule = Rule.parse(self.conflict_rule)
        except ValueError as exc:
            raise bad("conflict_rule", str(exc)) from None
        if not rule.coordinated:
            raise bad("conflict_rule", "DAgger rolls out under a coordinating rule, not 'revert'")
        from mapf_fleet.grid.guidance_made import GuidanceSource

        try:
            GuidanceSource.parse(self.guidance)
        except ValueError as exc:
            raise bad("guidance", str(exc)) from None
        if rule.is_lacam:
            raise bad("conflict_rule", "the planning arbiter executes its plan, not the policy's "
                                       "moves: roll out under a PIBT rule such as 'pibt_anchor'")
        from .labeller import LABELLERS

        if self.labeller not in LABELLERS:
            raise bad("labeller", f"must be one of {LABELLERS}")
        if self.committed_planner not in COMMITTED_PLANNERS:
            raise bad("committed_planner", f"must be one of {COMMITTED_PLANNERS}")
        if self.ranking not in Q_RANKINGS:
            raise bad("ranking", f"must be one of {Q_RANKINGS}")
        if self.loss not in LOSSES:
            raise bad("loss", f"must be one of {LOSSES}")
        if self.observation is not None and self.observation not in OBSERVATIONS:
            raise bad("observation", f"must be one of {OBSERVATIONS} or null (the init "
                      "checkpoint's)")
        for name in ("rounds", "episodes_per_round", "label_interval", "label_backoff_max",
                     "num_cpus", "num_workers",
                     "seq_len", "batch_windows", "threads", "heldout_count", "ceiling_count", "stuck_window",
                     "committed_max_nodes", "committed_restarts",
                     "ceiling_lifelong_count"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise bad(name, "must be an integer >= 1")
        for name in ("late_tasks_from", "burn_in", "updates_per_round", "max_plan_slack", "seed",
                     "planner_seed", "heldout_seed", "committed_replan_every", "ceiling_seed",
                     "ceiling_agreement_episodes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise bad(name, "must be an integer >= 0")
        for name in ("beta0", "beta_decay"):
            if not 0.0 <= float(getattr(self, name)) <= 1.0:
                raise bad(name, "must be in [0, 1]")
        for name in ("label_time_limit", "committed_budget", "max_plan_factor", "lr", "grad_clip",
                     "state_interval_seconds"):
            if not float(getattr(self, name)) > 0:
                raise bad(name, "must be > 0")
        if self.anchor_patience is not None and (
                isinstance(self.anchor_patience, bool) or not isinstance(self.anchor_patience, int)
                or self.anchor_patience < 0):
            raise bad("anchor_patience", "must be an integer >= 0 or null (the rule's)")
        if not 0.0 <= float(self.wait_label_cap) <= 1.0:
            raise bad("wait_label_cap", "must be in [0, 1]")
        if float(self.margin) < 0:
            raise bad("margin", "must be >= 0")
        if self.device not in ("auto", "cpu", "cuda") and not str(self.device).startswith("cuda:"):
            raise bad("device", "must be 'auto', 'cpu', 'cuda' or 'cuda:N'")
        if not self.tasks:
            raise bad("tasks", "needs at least one task")
        for name in ("tasks", "late_tasks", "ceiling", "ceiling_lifelong"):
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


def config_from_dict(data: dict, source: str = "<dict>", quiet: bool = False) -> DaggerConfig:
    """Build a config from a mapping; the deprecated keys (`shield`, `preferences`) are read as
    their new names (`mapf_fleet.aliases`), with a warning unless `quiet`."""
    if not isinstance(data, dict):
        raise DaggerConfigError(f"{source}: top level must be a mapping")
    try:
        data = renamed_keys(data, source, quiet)
    except ValueError as exc:
        raise DaggerConfigError(str(exc)) from None
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


