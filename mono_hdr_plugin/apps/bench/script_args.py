"""The arguments the scripts in benchmarks/ share, declared one way.

Each script builds its parser with `script_parser(__doc__)`, adds the common arguments it takes
(`add_out`, `add_scenes`, `add_methods`, `add_count`, `add_seconds`, `add_threads`,
`add_overrides`, `add_variants`) and then its own. Numbers are checked by the flag rules (`core.validation`), and
overrides are read by `runs.parse_override`, as `mono-hdr bench` reads them.
"""

import argparse
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from mono_hdr_plugin.apps.bench.runs import parse_override
from mono_hdr_plugin.core.validation import POSITIVE, Rule, at_least

Override = tuple[str, Any]


def script_parser(doc: str | None) -> argparse.ArgumentParser:
    """A parser whose description is the first paragraph of the script's docstring."""
    return argparse.ArgumentParser(description=(doc or "").split("\n\n")[0].strip())


def ruled(kind: type, rule: Rule) -> Callable[[str], Any]:
    """An argparse type: `kind(text)`, refused unless finite and within `rule` (the flag rules' words)."""

    def convert(text: str) -> Any:
        value = kind(text)
        if not (isinstance(value, int) or math.isfinite(value)) or not rule.accepts(value):
            raise argparse.ArgumentTypeError(f"must be {rule.describe(kind is int)}, got {text}")
        return value

    convert.__name__ = kind.__name__  # argparse names the type in its messages
    return convert


COUNT = ruled(int, at_least(1))
"""The argparse type of a count: an integer >= 1."""


def add_out(parser: argparse.ArgumentParser, default: Path | None, help: str | None = None) -> None:
    """--out: where the results go (required when there is no default)."""
    parser.add_argument("--out", type=Path, default=default, required=default is None, help=help)


def add_scenes(parser: argparse.ArgumentParser, default: str | Sequence[str]) -> None:
    """--scene NAME (a single default) or --scenes NAME... (a list of defaults): built-in studio scenes."""
    if isinstance(default, str):
        parser.add_argument("--scene", default=default, help="built-in studio scene")
    else:
        parser.add_argument("--scenes", nargs="+", default=list(default), help="built-in studio scenes")


def add_methods(parser: argparse.ArgumentParser, default: str | Sequence[str]) -> None:
    """--method NAME (a single default) or --methods NAME... (a list of defaults)."""
    if isinstance(default, str):
        parser.add_argument("--method", default=default, help="method (`mono-hdr methods` lists them)")
    else:
        parser.add_argument("--methods", nargs="+", default=list(default), help="methods (`mono-hdr methods`)")


def add_count(parser: argparse.ArgumentParser, flag: str, default: int | None, help: str | None = None) -> None:
    """A count >= 1: --steps, --repeats, --eval-views..."""
    parser.add_argument(flag, type=COUNT, default=default, help=help)


def add_seconds(parser: argparse.ArgumentParser, default: float, flag: str = "--seconds") -> None:
    """A training-time budget in seconds (> 0)."""
    parser.add_argument(flag, type=ruled(float, POSITIVE), default=default, help="training seconds per run")


def add_threads(parser: argparse.ArgumentParser, default: int | None = None) -> None:
    """--threads: torch threads (default: torch's own count)."""
    parser.add_argument(
        "--threads", type=COUNT, default=torch.get_num_threads() if default is None else default, help="torch threads"
    )


def add_overrides(parser: argparse.ArgumentParser) -> None:
    """--set KEY=VALUE ...: dotted config paths set on top of the preset (read with `overrides`)."""
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="overrides of the run's config, e.g. backbone.field.color_activation=sigmoid",
    )


def overrides(texts: Sequence[str], prefix: str = "") -> tuple[Override, ...]:
    """KEY=VALUE texts -> (dotted path, value) pairs, each path under `prefix`."""
    return tuple(parse_override(f"{prefix}{text}") for text in texts)


def add_variants(parser: argparse.ArgumentParser, example: str) -> None:
    """--variant (repeatable): 'base' or 'name=value,name=value' (read with `variant_overrides`)."""
    parser.add_argument(
        "--variant",
        action="append",
        default=None,
        help=f"'base' or name=value,... overrides (e.g. {example}); repeat for more; default: base",
    )


def variant_overrides(text: str, prefix: str = "") -> tuple[Override, ...]:
    """'base' -> (); 'name=value,name=value' -> the overrides, each path under `prefix`."""
    return () if text == "base" else overrides(text.split(","), prefix)
