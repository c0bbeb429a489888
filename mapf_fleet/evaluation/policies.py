"""What `--checkpoint` names: a checkpoint file, or a reference ("heuristic", "lacam", "pibt").

Decentralized policies (learned, heuristic) implement the batched interface the runner steps:
`reset(num_envs, num_agents)` then `act(obs (B,N,C,9,9), positions (B,N,2)) -> actions (B,N)`,
the observations built as the policy's `observation` says ("paper", C = 6, or "cost_to_go",
C = 7: a checkpoint's `model_config.observation`);
under a coordinated conflict rule (`PolicySpec.conflict_rule == "pibt"`, ...) the runner calls
`rank(obs, positions, tick) -> rankings (B,N,5)` instead, arbitrates them with
`coordination.factory.make_shield`'s layer, and tells the policy what was executed with
`executed(actions (B,N))` (DCC's last-action input).
Centralized planners are `planners.ClassicalPlanner` objects, replayed by the runner.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapf_fleet.coordination.planners import PLANNER_NAMES
from mapf_fleet.coordination.rules import FLEET_GUIDANCE, PIBT_RULES, REVERT, Rule
from mapf_fleet.coordination.ranking import (DEFAULT_RANKING, Q_RANKINGS, RANKINGS, default_ranking,
                                             recorded_ranking)

HEURISTIC = "heuristic"
REFERENCE_NAMES = (HEURISTIC, *PLANNER_NAMES)
# revert: the paper's environment (conflicting moves are reverted); pibt: CS-PIBT over the
# rankings; pibt_anchor: the same with the top-priority agent on its distance order
# (`PIBTShield(anchor=True)`); _swap, _hindrance: the PIBT variants (coordination.pibt)
# "+PIBT", "+PIBT-anchor", "+PIBT-anchor-swap", ..., "+LaCAM"
RULE_LABELS = {**{rule: "+PIBT" + "".join(f"-{part}" for part in rule.split("_")[1:])
                  for rule in PIBT_RULES}, "lacam": "+LaCAM"}


@dataclass(frozen=True)
class PolicySpec:
    """A picklable description of a policy, turned into an object in each worker process."""

    kind: str  # "checkpoint" | "heuristic" | "planner"
    name: str  # the row label of the tables
    path: str | None = None  # checkpoint file
    algorithm: str | None = None  # planner algorithm
    planner_time_limit: float = 10.0
    planner_seed: int = 0
    device: str = "cpu"
    conflict_rule: str = REVERT  # one of CONFLICT_RULES (decentralized policies only)
    ranking: str | None = None  # the ranking asked for under the rule (None: the default)
    # a checkpoint's recorded rankings (metadata `rankings`), ((rule, ranking), ...): its default
    rankings: tuple[tuple[str, str], ...] = ()
    # a checkpoint's metadata guidance (what its heuristic channels were trained on; None: not
    # recorded, `default_guidance` then)
    recorded_guidance: str | None = None
    planning_budget: float | None = None  # rule "lacam": seconds per re-plan (None: default)
    # the guidance graph every distance reads (`GuidanceSource` spelling): observations, rule
    guidance: str = "none"

    @property
    def is_planner(self) -> bool:
        return self.kind == "planner"

    @property
    def resolved_ranking(self) -> str:
        """The ranking the conflict rule arbitrates: the heuristic ranks by distance (its choice
        first: it follows a closer move), a checkpoint by its Q-values: `ranking` when given,
        else the ranking the checkpoint records for the rule, else the rule's default."""
        if self.ranking is not None:
            return self.ranking
        if self.kind == "heuristic":
            return "distance"
        return default_ranking(self.conflict_rule, dict(self.rankings))

    @property
    def default_guidance(self) -> str:
        """The guidance the spec runs under when none is asked for: what its checkpoint records
        (the graph its heuristic channels were trained to read), else the fleet's
        (`coordination.rules.FLEET_GUIDANCE`, what `mapf-fleet up` reads). Under the paper's
        rule `revert` (the paper's protocol, whose figures are unguided) none, and a centralized
        planner plans unguided."""
        if self.recorded_guidance is not None and not self.is_planner:
            return self.recorded_guidance
        return "none" if self.is_planner or self.conflict_rule == REVERT else FLEET_GUIDANCE


def with_conflict_rule(spec: PolicySpec, rule: str, ranking: str | None = None) -> PolicySpec:
    """`spec` under a conflict rule; the row label says which (and the ranking when given)."""
    from dataclasses import replace

    rule = Rule.parse(rule, "--conflict-rule").name
    if ranking is not None and ranking not in RANKINGS:
        raise ValueError(f"--ranking must be among {RANKINGS}, got {ranking!r}")
    if rule == REVERT or spec.is_planner:
        return spec
    if spec.kind == "heuristic" and ranking not in (None, "distance"):
        raise ValueError(f"--ranking {ranking}: the heuristic has no Q-values "
                         f"(its ranking is 'distance'); the Q rankings are {Q_RANKINGS}")
    # the ranking is named unless it comes from the rule's table: asked for, or the checkpoint's
    named = ranking if ranking is not None else recorded_ranking(rule, dict(spec.rankings))
    label = RULE_LABELS.get(rule, "+" + rule) + ("" if named is None else f"({named})")
    return replace(spec, name=f"{spec.name} {label}", conflict_rule=rule, ranking=ranking)


def with_guidance(specs: list[PolicySpec], values) -> list[PolicySpec]:
    """Each decentralized spec once per guidance value (`GuidanceSource`, parsed here: a bad
    value is refused before any worker starts), labelled " +G" unless "none"; planners plan
    unguided (one row)."""
    from dataclasses import replace

    from mapf_fleet.grid.guidance_made import GuidanceSource

    out = []
    for spec in specs:
        # not given: what the checkpoint was trained to read (metadata guidance), else the fleet's
        # (`PolicySpec.default_guidance`)
        given = values if values is not None else [spec.default_guidance]
        sources = list(dict.fromkeys(GuidanceSource.parse(v) for v in given))
        for k, source in enumerate(sources):
            if spec.is_planner or spec.conflict_rule == REVERT and spec.kind != "checkpoint":
                if k == 0:
                    out.append(spec)
                continue
            label = "" if source.kind == "none" else f" +{source.label}"
            out.append(replace(spec, name=spec.name + label, guidance=str(source)))
    return out


def parse_policy(arg: str, *, device: str = "cpu", planner_time_limit: float = 10.0, planner_seed: int = 0) -> PolicySpec:
    """`heuristic`, `lacam`, `pibt`, or a path to a checkpoint file (must exist; its metadata is
    read here, once: a bad file is refused before any worker starts)."""
    if arg == HEURISTIC:
        return PolicySpec("heuristic", "heuristic")
    if arg in PLANNER_NAMES:
        return PolicySpec(
            "planner", arg.upper() if arg == "pibt" else "LaCAM", algorithm=arg,
            planner_time_limit=planner_time_limit, planner_seed=planner_seed,
        )
    path = Path(arg)
    if not path.is_file():
        raise FileNotFoundError(f"--checkpoint {arg!r}: no such file (or use one of {', '.join(REFERENCE_NAMES)})")
    from mapf_fleet.models.checkpoint import read_checkpoint

    meta = read_checkpoint(path)[1]
    rankings = meta.get("rankings") or {}
    return PolicySpec("checkpoint", path.stem, path=str(path), device=device,
                      rankings=tuple(sorted(rankings.items())),
                      recorded_guidance=(None if meta.get("guidance") is None
                                         else str(meta["guidance"])))


def unique_names(specs: list[PolicySpec]) -> list[PolicySpec]:
    """Row labels must be unique: a checkpoint stem used twice gets its folder name, and any
    label still repeated gets "#2", "#3"..."""
    from collections import Counter
    from dataclasses import replace

    counts = Counter(spec.name for spec in specs)
    used: set[str] = set()
    out = []
    for spec in specs:
        name = spec.name
        if counts[name] > 1 and spec.path:
            name = f"{Path(spec.path).resolve().parent.name}/{spec.name}"
        base, k = name, 2
        while name in used:
            name, k = f"{base}#{k}", k + 1
        used.add(name)
        out.append(replace(spec, name=name))
    return out


def _tie_breakers(tick: int, batch: int, agents: int) -> np.ndarray:
    from mapf_fleet.coordination.ranking import tie_breakers

    return np.broadcast_to(tie_breakers(np.arange(agents), tick), (batch, agents, 5))


class HeuristicBatchPolicy:
    """The non-learned reference (`mapf_fleet.grid.policies.heuristic_policy`), batched.
    Under the shield its ranking is the distance order: plain PIBT."""

    observation = "paper"  # it reads the heuristic bits only

    def __init__(self, ranking: str = "distance"):
        self.ranking = ranking

    def reset(self, num_envs: int, num_agents: int) -> None:
        pass

    def rank(self, obs: np.ndarray, positions: np.ndarray, tick: int) -> np.ndarray:
        from mapf_fleet.coordination.ranking import rank_actions

        return rank_actions(obs, mode="distance", ties=_tie_breakers(tick, *obs.shape[:2]))

    def executed(self, actions: np.ndarray) -> None:
        pass

    def act(self, obs: np.ndarray, positions: np.ndarray) -> np.ndarray:
        from mapf_fleet.grid.policies import heuristic_policy

        batch, agents = obs.shape[:2]
        return np.asarray(heuristic_policy(obs.reshape(batch * agents, *obs.shape[2:]))).reshape(batch, agents)


class CheckpointBatchPolicy:
    """A learned checkpoint through `mapf_fleet.models.policy.LearnedPolicy`."""

    def __init__(self, path: str, device: str = "cpu", ranking: str = DEFAULT_RANKING):
        from mapf_fleet.models.checkpoint import load_checkpoint
        from mapf_fleet.models.policy import LearnedPolicy

        model, metadata = load_checkpoint(path)
        padding = (metadata or {}).get("obs_padding", "obstacle")
        if padding != "obstacle":
            # The environment pads off-map cells as obstacles (docs/architecture.md); a model
            # trained with another padding would be evaluated on inputs it never saw.
            raise ValueError(f"{path}: obs_padding is {padding!r}, the evaluator's environment pads 'obstacle'")
        self.metadata = metadata
        self.policy = LearnedPolicy(model, device)
        self.observation = self.policy.observation
        self.ranking = ranking

    def reset(self, num_envs: int, num_agents: int) -> None:
        self.policy.reset(num_envs, num_agents)

    def keep(self, rows: list[int]) -> None:
        """Keep only these episodes' recurrent state (finished episodes leave the batch)."""
        index = list(rows)
        self.policy.hidden = self.policy.hidden[index]
        if getattr(self.policy, "last_actions", None) is not None:
            self.policy.last_actions = self.policy.last_actions[index]

    def act(self, obs: np.ndarray, positions: np.ndarray) -> np.ndarray:
        actions = self.policy.act(obs, positions)
        if hasattr(actions, "detach"):
            actions = actions.detach().cpu().numpy()
        return np.asarray(actions, dtype=np.int64)

    def rank(self, obs: np.ndarray, positions: np.ndarray, tick: int) -> np.ndarray:
        """Preference orders (B, N, 5) from this step's Q-values (the step runs here)."""
        from mapf_fleet.coordination.ranking import rank_actions

        self.act(obs, positions)
        return rank_actions(obs, self.policy.q_values, self.ranking,
                            ties=_tie_breakers(tick, *obs.shape[:2]))

    def executed(self, actions: np.ndarray) -> None:
        """What the shield executed becomes DCC's last action (its recurrent input)."""
        self.policy.set_last_actions(actions)


def build_policy(spec: PolicySpec):
    """The object the runner steps for `spec` (a batch policy or a ClassicalPlanner)."""
    if spec.kind == "heuristic":
        return HeuristicBatchPolicy(spec.resolved_ranking)
    if spec.kind == "planner":
        from mapf_fleet.coordination.planners import ClassicalPlanner

        return ClassicalPlanner(spec.algorithm, spec.planner_time_limit, spec.planner_seed)
    if spec.kind == "checkpoint":
        return CheckpointBatchPolicy(spec.path, spec.device, spec.resolved_ranking)
    raise ValueError(f"unknown policy kind {spec.kind!r}")
