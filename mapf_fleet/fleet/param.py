"""A knob as data: a node parameter (`Param`: default, description, check, whether it may
change during a run, one refusal message) and how `mapf-fleet up` offers it (`Option`: flag,
help, when it applies). The tables of every node's parameters are in `fleet.parameters`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable


@dataclass(frozen=True)
class Applies:
    """When an `up` option applies: `test(facts)` (facts: `up_options.UpFacts`, what the run
    will be: real robots, a Nav2 map, an instance file, the task source); an option given where
    it does not apply is refused as '<flag> <refusal>'."""
    test: Callable[[object], bool]
    refusal: str


REAL_ROBOTS = Applies(lambda f: f.real_robots, "applies to --real-robots")
NAV2_MAP = Applies(lambda f: f.nav2_map, "applies to a Nav2 map (--map F.yaml)")
GENERATED_MAP = Applies(lambda f: not (f.instance or f.map),
                        "applies to a generated map, not to --instance or --map")
LIFELONG = Applies(lambda f: f.task_source == "lifelong", "applies to --task-source lifelong")


@dataclass(frozen=True)
class Option:
    """How `mapf-fleet up` offers a parameter: `flag` ("--size"), `help` (empty: the
    parameter's description; the table's default is appended unless the help states one),
    `applies` (every one must hold, else the option is refused), argparse's `metavar` and
    `nargs`, and `part`: which value of a multi-value option this parameter takes (`--origin X
    Y` sets origin_x and origin_y; the first part declares the option)."""
    flag: str
    help: str = ""
    applies: tuple = ()
    metavar: object = None
    nargs: object = None
    part: int | None = None


@dataclass(frozen=True)
class Param:
    default: object
    description: str
    check: Callable[[object], bool] | None = None
    condition: str = ""  # what `check` demands, as a message says it ("> 0")
    choices: tuple = ()
    runtime: bool = False  # may change during a run (`mapf-fleet param set`)
    option: Option | None = None  # `mapf-fleet up`'s option for it (None: none)

    @property
    def type(self) -> type:
        return type(self.default)

    def coerce(self, value):
        """`value` as this parameter's type (an int for a float parameter becomes a float; rcl
        refuses the type otherwise); TypeError when it cannot be."""
        kind = self.type
        if kind is bool:
            if isinstance(value, bool):
                return value
        elif kind is int:
            if isinstance(value, int) and not isinstance(value, bool):
                return value
        elif kind is float:
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                return float(value)
        elif kind is str:
            if isinstance(value, str):
                return value
            if value is None:
                return ""
        raise TypeError(kind.__name__)

    def problem(self, value) -> str:
        """Why `value` is refused ("" when it is not): 'must be > 0, got -1'."""
        try:
            value = self.coerce(value)
        except TypeError:
            what = {int: "an integer", float: "a number", str: "text",
                    bool: "true or false"}[self.type]
            extra = f" {self.condition}" if self.condition else ""
            return f"must be {what}{extra}, got {value!r}"
        if isinstance(value, float) and not math.isfinite(value):
            return f"must be a finite number, got {value!r}"
        if self.choices and value not in self.choices:
            return f"must be one of {', '.join(c or repr(c) for c in self.choices)}, got {value!r}"
        if self.check is not None and not self.check(value):
            return f"must be {self.condition}, got {value!r}"
        return ""
