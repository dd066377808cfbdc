"""Flag values checked before any work is done: one mechanism for every config dataclass.

A config dataclass lists the range of its numeric fields in a class-level table,

    flag_rules: ClassVar[dict[str, Rule]] = {"lr": POSITIVE, "hidden": at_least(1), ...}

and `check_flags(config)` walks the config (nested dataclasses included) and refuses the first
value out of range, naming the flag as the command line spells it (`--backbone.lr-means`).
Every numeric field is also checked to be finite, with a rule or without one: NaN or Inf is
never a meaningful learning rate, weight, size or exposure, and a NaN learning rate would
otherwise run to the end skipping every step. Rates, sizes and exposures must be positive;
loss weights may be 0 (the term is off) but not negative. A text field with a fixed set of values
lists them with `one_of("sequential", "ray")`. A check that involves two flags, which no rule
can express, raises FlagError itself, naming both flags.
"""

import dataclasses
import math
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import tyro


class FlagError(ValueError):
    """A command-line flag (or config field) whose value cannot work."""


@dataclass(frozen=True)
class Rule:
    """An allowed interval of a numeric field (bounds None: unbounded on that side)."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def accepts(self, value: float) -> bool:
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return self.high is None or (value < self.high if self.high_open else value <= self.high)

    def describe(self, integer: bool) -> str:
        kind = "an integer" if integer else "a number"
        if self.high is None:
            if self.low is None:
                return f"a finite {kind.split()[-1]}"
            if self.low == 0 and self.low_open:
                return "a positive integer" if integer else "a positive number"
            return f"{kind} {'>' if self.low_open else '>='} {_bound(self.low)}"
        if self.low is None:
            return f"{kind} {'<' if self.high_open else '<='} {_bound(self.high)}"
        return (
            f"{kind} in {'(' if self.low_open else '['}{_bound(self.low)}, {_bound(self.high)}"
            f"{')' if self.high_open else ']'}"
        )


@dataclass(frozen=True)
class Choice:
    """The allowed values of a text field."""

    choices: tuple[str, ...]

    def accepts(self, value: str) -> bool:
        return value in self.choices

    def describe(self) -> str:
        return f"one of {', '.join(self.choices)}"


def one_of(*choices: str) -> Choice:
    return Choice(choices)


def _bound(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


def at_least(minimum: float) -> Rule:
    return Rule(low=minimum)


def between(low: float, high: float, low_open: bool = False, high_open: bool = False) -> Rule:
    return Rule(low=low, high=high, low_open=low_open, high_open=high_open)


POSITIVE = Rule(low=0, low_open=True)
"""Rates, sizes, exposures, scales: > 0."""
NON_NEGATIVE = at_least(0)
"""Counts that may be zero, thresholds, regularisation strengths: >= 0 (loss terms: LOSS_WEIGHT)."""
LOSS_WEIGHT = between(0, 1e6)
"""A loss term's weight: past 1e6 it drowns every other term, and soon overflows float32 (NaN steps)."""
MAX_IMAGE_SIDE = 4096
"""The largest studio image a side (--resolution, bench sizes): beyond, one render takes days and a
scene tens of GB."""
FRACTION = between(0, 1)
SEED = between(0, 2**32 - 1)
ANY_FINITE = Rule()
"""Any finite value is meaningful (biases, offsets)."""


def numeric(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def rules_of(config_class: type) -> dict[str, Rule | Choice]:
    """The flag_rules table of a config dataclass and of its bases (subclass entries win)."""
    rules: dict[str, Rule | Choice] = {}
    for cls in reversed(config_class.__mro__):
        rules.update(vars(cls).get("flag_rules", {}))
    return rules


def _omits_prefix(annotation: Any) -> bool:
    return typing.get_origin(annotation) is typing.Annotated and any(
        marker is tyro.conf.OmitArgPrefixes for marker in typing.get_args(annotation)[1:]
    )


def iter_flags(config: Any, prefix: str = "--") -> Iterator[tuple[str, Any, Rule | Choice | None]]:
    """(flag, value, rule) of every leaf field of a config dataclass, nested configs flattened the
    way tyro names them (a field annotated OmitArgPrefixes adds no prefix)."""
    hints = typing.get_type_hints(type(config), include_extras=True)
    rules = rules_of(type(config))
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        name = field.name.replace("_", "-")
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            yield from iter_flags(value, prefix if _omits_prefix(hints.get(field.name)) else f"{prefix}{name}.")
        else:
            yield f"{prefix}{name}", value, rules.get(field.name)


def check_flags(config: Any) -> None:
    """Raise FlagError naming the first flag of `config` that is non-finite, out of its rule or not one
    of its choices."""
    for flag, value, rule in iter_flags(config):
        for item in value if isinstance(value, (tuple, list)) else (value,):
            if isinstance(rule, Choice):
                if item is not None and not rule.accepts(item):
                    raise FlagError(f"{flag} must be {rule.describe()}, got {item!r}")
                continue
            if not numeric(item):
                continue
            integer = isinstance(item, int)
            if not (integer or math.isfinite(item)) or (rule is not None and not rule.accepts(item)):
                wanted = (rule or ANY_FINITE).describe(integer)
                raise FlagError(f"{flag} must be {wanted}, got {item}")
