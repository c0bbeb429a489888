"""The factory of the coordination layer: a conflict rule's arbiter, built in one place (the top of
the layer: it knows every rule's class).

`make_shield(rule, grid, goals, ...)` returns None for `revert` (the environment's own conflict
resolution), a `pibt.PIBTShield` with the options the rule carries, or for `lacam` a
`plan.PlanKeeper` with the `plan.ARBITER` options. Every arbiter has the same interface (`step`,
`set_goals`, `reset`, `advance_priorities`, `goals`, `priorities`, `base_priority`, `tick`) and
reads its distances from the map's shared table under `guidance`. An `_epibt` rule's arbiter is
an `epibt.EPIBTShield` (a `PIBTShield` whose rankings EPIBT's operations reorder), an `_lns`
rule's an `lns.LNSShield` (one whose rankings a windowed plan reorders).
"""

from __future__ import annotations

from .epibt import EPIBTShield
from .lns import LNSShield
from .pibt import PIBTShield
from .plan import ARBITER, PlanKeeper
from .rules import Rule


def make_shield(rule: "Rule | str", grid, goals, planning_budget: float | None = None,
                anchor_patience: int | None = None, guidance=None):
    """The arbiter of `rule` (a `Rule` or its name) on `grid` for agents heading to `goals`
    (N, 2). planning_budget: seconds per re-plan of the `lacam` rule (default the `ARBITER`'s);
    anchor_patience: a PIBT rule's anchor patience (default the rule's); guidance: a
    `grid.guidance.Guidance` for the map, or None."""
    rule = Rule.parse(rule)
    if not rule.coordinated:
        return None
    if rule.is_lacam:
        return PlanKeeper(grid, goals, ARBITER, guidance=guidance,
                          planning_budget=planning_budget)
    if rule.epibt:
        return EPIBTShield(grid, goals, **rule.pibt_options(), anchor_patience=anchor_patience,
                           guidance=guidance, horizon=rule.horizon)
    if rule.lns:
        return LNSShield(grid, goals, **rule.pibt_options(), anchor_patience=anchor_patience,
                         guidance=guidance, window=rule.window)
    return PIBTShield(grid, goals, **rule.pibt_options(), anchor_patience=anchor_patience,
                      guidance=guidance)


__all__ = ["make_shield"]
