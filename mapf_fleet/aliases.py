"""The deprecated spellings still accepted for one release, each with one warning line on
stderr naming the old and the new spelling. The per-tick arbitration rule was the `shield`
and is the conflict rule (`conflict_rule`, its unshielded value `revert` was `none`); a
robot's ordered moves were its `preferences` and are its ranking (`ranking`). Checkpoints
written before keep the old keys in their `training_config`: readers map them silently
(`quiet`), a file the user edits gets the warning."""

from __future__ import annotations

import sys
from typing import Any, Mapping

# command-line options of `mapf-fleet evaluate` (and `--lifelong`): old -> new
OPTIONS = {"--shield": "--conflict-rule", "--preferences": "--ranking"}
# keys of the trainer's and DAgger's configurations: old -> new
CONFIG_KEYS = {"shield": "conflict_rule", "shield_preferences": "ranking", "preferences": "ranking",
               "shield_replay": "replay_action"}
# ROS parameters of the policy nodes (params files, `-p`): old -> new
PARAMETERS = {"preference_mode": "ranking"}
# values of a conflict rule: old -> new
RULE_VALUES = {"none": "revert"}


def warn(where: str, old: str, new: str) -> None:
    print(f"{where}: {old} is deprecated, use {new}", file=sys.stderr)


def rule_value(value: Any, where: str, quiet: bool = False) -> Any:
    """A conflict rule's value with its deprecated spelling replaced."""
    if isinstance(value, str) and value in RULE_VALUES:
        if not quiet:
            warn(where, repr(value), repr(RULE_VALUES[value]))
        return RULE_VALUES[value]
    return value


def renamed_options(argv: list[str], where: str) -> list[str]:
    """`argv` with the deprecated options (`--shield x`, `--shield=x`) spelled the new way, and
    a deprecated conflict rule value after `--conflict-rule` replaced."""
    out, rule_values = [], False
    for arg in argv:
        name, eq, value = arg.partition("=")
        if name in OPTIONS:
            warn(where, name, OPTIONS[name])
            name = OPTIONS[name]
            arg = name + eq + value
        if arg.startswith("--"):
            rule_values = name == "--conflict-rule"
            if rule_values and eq:
                arg = name + "=" + rule_value(value, f"{where}: --conflict-rule")
        elif rule_values:
            arg = rule_value(arg, f"{where}: --conflict-rule")
        out.append(arg)
    return out


def renamed_keys(data: Mapping[str, Any], where: str, quiet: bool = False) -> dict[str, Any]:
    """A configuration mapping with the deprecated keys (and the deprecated conflict rule
    value) spelled the new way; a key given under both spellings is an error naming both."""
    out = dict(data)
    for old, new in CONFIG_KEYS.items():
        if old not in out:
            continue
        if new in out:
            raise ValueError(f"{where}: {old!r} and {new!r} are the same key (the first is "
                             f"its deprecated spelling): give only {new!r}")
        if not quiet:
            warn(where, f"key {old!r}", repr(new))
        out[new] = out.pop(old)
    if "conflict_rule" in out:
        out["conflict_rule"] = rule_value(out["conflict_rule"], f"{where}: conflict_rule", quiet)
    return out
