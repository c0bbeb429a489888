"""The conflict rules, as values: the bottom of the coordination layer (standard library only).

A conflict rule says what stands between the robots' ranked moves and the moves commanded:

  revert        the paper's environment: conflicting moves are reverted, no coordination layer
  pibt[_anchor|_patient][_swap][_hindrance]
                PIBT over the rankings (`pibt.PIBTShield`), with its options in that order:
                anchor (the top agent follows its distance order), patient (an anchor that waits
                `ANCHOR_PATIENCE` ticks), swap (lacam3's corridor swap), hindrance (equally short
                moves ordered by the neighbours they block); docs/coordination.md
  pibt[_anchor|_patient][_swap]_epibt
                the same PIBT rules with EPIBT's longer horizon: each agent's first move is the
                first of a multi-step operation chosen in priority order (`EPIBT_HORIZON` moves;
                `epibt.EPIBTShield`; no hindrance: both order the first moves)
  pibt[_anchor|_patient][_swap]_lns
                the same PIBT rules under a windowed plan repaired every tick (WPPL's windowed
                PIBT + LNS): each agent's first move is the first of its path in a plan of
                `LNS_WINDOW` ticks for all agents (`lns.LNSShield`; no hindrance)
  lacam         the planning arbiter: a kept LaCAM plan, the anchored PIBT step with swap as its
                fallback (`plan.PlanKeeper`)

A rule name enters the project at its boundaries (the CLI, a ROS parameter, a config file, a
checkpoint's metadata) and is parsed there, once, by `Rule.parse`: the one place that knows the
spelling and the one refusal message. Everything below the boundary passes the `Rule` value.
`Rule.default_ranking` is the ranking a learned policy uses under the rule when neither the user
nor the checkpoint names one (derived from the rule's options: see the property).
"""

from __future__ import annotations

from dataclasses import dataclass

# The options a PIBT rule's name may add to "pibt", in the order they appear in it
RULE_OPTIONS = ("anchor", "swap", "hindrance")
REVERT = "revert"
LACAM = "lacam"
# Every PIBT rule: the original four first, then hindrance, then the patient anchor
PIBT_RULES = ("pibt", "pibt_anchor", "pibt_swap", "pibt_anchor_swap", "pibt_hindrance",
              "pibt_anchor_hindrance", "pibt_swap_hindrance", "pibt_anchor_swap_hindrance",
              "pibt_patient", "pibt_patient_swap", "pibt_patient_hindrance",
              "pibt_patient_swap_hindrance")
COORDINATED_RULES = (*PIBT_RULES, LACAM)
# The PIBT rules with EPIBT's multi-step operations (suffix "_epibt"; hindrance excluded)
EPIBT = "epibt"
EPIBT_RULES = tuple(f"{rule}_{EPIBT}" for rule in PIBT_RULES if "hindrance" not in rule)
# The PIBT rules under a windowed plan repaired by LNS (suffix "_lns"; hindrance excluded)
LNS = "lns"
LNS_RULES = tuple(f"{rule}_{LNS}" for rule in PIBT_RULES if "hindrance" not in rule)
CONFLICT_RULES = (*COORDINATED_RULES, REVERT, *EPIBT_RULES, *LNS_RULES)
# The fleet's rule: what `mapf-fleet up` runs and `evaluate` measures by default. The windowed
# plan repaired every tick over the anchored PIBT with swap: with FLEET_GUIDANCE, 1.22x / 1.41x /
# 1.21x plain `pibt_anchor_swap`'s lifelong throughput inside POGEMA (random / mazes / warehouse,
# maps nothing was tuned on); unguided at or above RHCR's published figures at 8 of 9 counts
# (docs/results.md, "A windowed plan repaired every tick (LNS)" and "A longer plan")
FLEET_RULE = "pibt_anchor_swap_lns"
# The fleet's guidance graph (a `grid.guidance_made.GuidanceSource` spelling): what `mapf-fleet
# up` reads and `evaluate` measures by default, for the heuristic and for a checkpoint that
# records no guidance of its own. The best graph that needs no per-map training: the hand-made
# highways were level or better for the shipped policy under `pibt_anchor_swap` on every family
# measured (docs/results.md, "Which guidance is the fleet's default, and why"), and under
# FLEET_RULE they are what lifts the warehouse to 1.2x (they cost 2-4 % on random maps and mazes:
# "A windowed plan repaired every tick (LNS)"); `--guidance none` is the unguided world, bit for
# bit.
FLEET_GUIDANCE = "highways"
# `patient`: the anchor waits until the top agent has gone this many ticks without getting closer
# to its goal than before; a plan or a policy may keep it waiting that long and it still reaches
# its goal within (patience + 1) x its distance ticks (docs/coordination.md; the value was chosen
# by the expert ceiling: the shortest patience that lifted it, docs/results.md, "The expert
# ceiling, second reading")
ANCHOR_PATIENCE = 32
# EPIBT's moves per operation (`epibt.EPIBTShield`). 3: long enough to see a head-on meeting or
# a stopping queue one cell beyond the next step (what one-step PIBT walks into), the length of
# the LoRR 2024 EPIBT's operations, and the operation set stays small (85 operations; each extra
# move multiplies it by about 4) so that a 2,048-agent tick stays within its budget in plain
# Python (measured: docs/results.md, "A longer horizon per tick (EPIBT)")
EPIBT_HORIZON = 3
# The `_lns` rules' plan (`lns.LNSShield`): ticks planned ahead, repairs a tick and robots a
# repair plans again. Chosen by measurement inside POGEMA (docs/results.md, "A windowed plan
# repaired every tick (LNS)" and "A longer plan"): 16 / 128 moved 0-6 % more goals than 8 / 64
# (most in the mazes) at 2.5x the tick, within issue 41's 50 ms at 64 agents and 1 s at 2,048
LNS_WINDOW = 16
LNS_ITERATIONS = 128
LNS_NEIGHBOURHOOD = 8
# the `_swap_lns` rules' executed tick swaps only for (or with) an agent that has spent this many
# ticks off its goal since it last came closer to it (`lns` module docstring; 3 and 8 measured,
# 8 kept)
LNS_SWAP_STALL = 8
# The learned rankings a rule picks by default (`Rule.default_ranking`; chosen by measurement,
# docs/results.md, "Which ranking under which rule")
ANCHORED_RANKING = "confidence"
UNANCHORED_RANKING = "q"


@dataclass(frozen=True)
class Rule:
    """One conflict rule. Build it with `Rule.parse(name)`; `str(rule)` is its name."""

    name: str
    kind: str  # "revert", "pibt" or "lacam"
    anchor: bool = False
    swap: bool = False
    hindrance: bool = False
    patient: bool = False
    horizon: int = 0  # EPIBT's moves per operation; 0: one-step PIBT (not an `_epibt` rule)
    plan: bool = False  # an `_lns` rule: a windowed plan repaired by LNS (`window` ticks)

    @classmethod
    def parse(cls, value: "Rule | str", what: str = "conflict rule") -> "Rule":
        """The rule named `value` (a `Rule` passes through); ValueError naming `what` and the
        value otherwise. The only place a rule's spelling is read."""
        if isinstance(value, Rule):
            return value
        if not isinstance(value, str) or value not in CONFLICT_RULES:
            raise ValueError(f"{what} must be one of {', '.join(CONFLICT_RULES)}; got {value!r}")
        if value in (REVERT, LACAM):
            return cls(value, value)
        parts = value.split("_")[1:]
        patient = "patient" in parts
        return cls(value, "pibt", anchor="anchor" in parts or patient, swap="swap" in parts,
                   hindrance="hindrance" in parts, patient=patient,
                   horizon=EPIBT_HORIZON if EPIBT in parts else 0,
                   plan=LNS in parts)

    @classmethod
    def pibt(cls, anchor: bool = False, swap: bool = False, hindrance: bool = False,
             patient: bool = False, epibt: bool = False, lns: bool = False) -> "Rule":
        """The PIBT rule with these options."""
        flags = {"anchor": anchor and not patient, "swap": swap, "hindrance": hindrance}
        names = [o for o in RULE_OPTIONS if flags[o]]
        return cls.parse("_".join(["pibt", *(["patient"] if patient else []), *names,
                                   *([EPIBT] if epibt else []), *([LNS] if lns else [])]))

    def __str__(self) -> str:
        return self.name

    @property
    def coordinated(self) -> bool:
        """A coordination layer commands the moves (every rule but `revert`)."""
        return self.kind != REVERT

    @property
    def is_pibt(self) -> bool:
        return self.kind == "pibt"

    @property
    def epibt(self) -> bool:
        """A PIBT rule with EPIBT's multi-step operations (`epibt.EPIBTShield`)."""
        return self.horizon > 0

    @property
    def lns(self) -> bool:
        """A PIBT rule under a windowed plan repaired by LNS (`lns.LNSShield`)."""
        return self.plan

    @property
    def window(self) -> int:
        """The `_lns` rules' ticks planned, `LNS_WINDOW` read now (as `LNSShield` reads the
        repairs when built: one place to change the plan); 0: not an `_lns` rule."""
        return LNS_WINDOW if self.plan else 0

    @property
    def is_lacam(self) -> bool:
        return self.kind == LACAM

    def pibt_options(self) -> dict[str, bool]:
        """{"anchor", "swap", "hindrance", "patient"}: `PIBTShield`'s keyword options (an
        `_epibt` rule's shield, `epibt.EPIBTShield`, takes `horizon` besides)."""
        if not self.is_pibt:
            raise ValueError(f"{self.name!r} is not a PIBT rule")
        return {"anchor": self.anchor, "swap": self.swap, "hindrance": self.hindrance,
                "patient": self.patient}

    @property
    def ranking_rule(self) -> "Rule":
        """The rule whose rankings this rule's robots submit: itself for a PIBT rule; for the
        planning arbiter its fallback step's anchored rule (it ranks LaCAM's root step and its
        fallback by the robots' rankings)."""
        return Rule.parse("pibt_anchor") if self.is_lacam else self

    @property
    def default_ranking(self) -> str:
        """`confidence` where the top agent is anchored (the network overrides the distance
        order only where it is sure, so the anchor's order and the policy's rarely fight), `q`
        otherwise; the planning arbiter takes its fallback rule's."""
        rule = self.ranking_rule
        return ANCHORED_RANKING if rule.anchor else UNANCHORED_RANKING


def rule_arg(value: str) -> str:
    """An argparse `type` for a rule name: the name, parsed here (argparse's one-line refusal
    carries `Rule.parse`'s message)."""
    import argparse

    try:
        return Rule.parse(value).name
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def parse_rules(values, what: str = "conflict rule") -> list[Rule]:
    """`Rule.parse` of each value (a CLI's list of rule names)."""
    return [Rule.parse(v, what) for v in values]


__all__ = ["Rule", "parse_rules", "rule_arg", "CONFLICT_RULES", "COORDINATED_RULES", "PIBT_RULES", "REVERT",
           "EPIBT_RULES", "EPIBT_HORIZON", "LNS_RULES", "LNS_WINDOW", "LNS_ITERATIONS",
           "LNS_NEIGHBOURHOOD", "LNS_SWAP_STALL",
           "LACAM", "FLEET_RULE", "FLEET_GUIDANCE", "ANCHOR_PATIENCE", "RULE_OPTIONS"]
