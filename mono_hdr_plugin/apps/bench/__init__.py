"""What accuracy costs in time: `mono-hdr bench curves`, `bench paper`, and what backbones add.

Every figure is measured in the run that reports it; results are JSON (with git commit,
machine facts and library versions), Markdown tables and matplotlib plots. Each finished run
is written at once, so an interrupted benchmark keeps it and resumes after it. Runs execute
in this process or on a Ray cluster (`--executor ray`), with the same results.
"""

from typing import Any

from mono_hdr_plugin.apps.bench.curves import BenchCurvesConfig, bench_curves
from mono_hdr_plugin.apps.bench.paper import BenchPaperConfig, bench_paper
from mono_hdr_plugin.core.registry import BACKBONES

BENCHMARKS = {"curves": (BenchCurvesConfig, bench_curves), "paper": (BenchPaperConfig, bench_paper)}


def all_benchmarks() -> dict[str, tuple[type, Any]]:
    """The benchmarks every pipeline has, plus those each registered backbone contributes
    (`Backbone.benchmarks`, e.g. the 3DGS rasteriser's `raster`)."""
    found = dict(BENCHMARKS)
    for entry in BACKBONES.available().values():
        for name, benchmark in entry.plugin.benchmarks().items():
            if name in found:
                raise ValueError(f"backbone {entry.name!r} contributes a benchmark named {name!r}, which exists "
                                 "already; rename it")
            found[name] = benchmark
    return found
