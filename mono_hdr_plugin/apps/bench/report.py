"""Shared pieces of the benchmark reports: number formatting, labels, matplotlib set-up."""

import contextlib
import math
from collections.abc import Callable, Iterator
from typing import Any


def fmt(value: float | None, digits: int = 2) -> str:
    return "n/a" if value is None or math.isnan(value) else f"{value:.{digits}f}"


def label(spec: dict[str, Any]) -> str:
    """backbone[-preset] / method [overrides] at N px (the size when not the scene's own) of a row's spec."""
    overrides = ", ".join(f"{path}={value}" for path, value in spec.get("overrides", ()))
    preset = f"-{spec['preset']}" if spec.get("preset") else ""
    size = f" at {spec['resolution']} px" if spec.get("resolution") else ""
    return f"{spec['backbone']}{preset} / {spec['method']}" + (f" [{overrides}]" if overrides else "") + size


def pyplot():
    """matplotlib's pyplot on the file-only Agg backend (no display on these machines)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


@contextlib.contextmanager
def report_on_exit(write_report: Callable[[], None]) -> Iterator[None]:
    """Write the Markdown/plots of the finished rows even when the run is interrupted."""
    try:
        yield
    finally:
        write_report()
