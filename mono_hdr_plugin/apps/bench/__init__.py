"""What accuracy costs in time: `mono-hdr bench curves`, `bench paper`, and the benchmarks plugins add.

Every figure is measured in the run that reports it; results are JSON (with git commit,
machine facts and library versions), Markdown tables and matplotlib plots. Each finished run
is written at once, so an interrupted benchmark keeps it and resumes after it. Runs execute
in this process or on a Ray cluster (`--executor ray`), with the same results.

Importing this package registers `cost`, `curves` and `paper` in `core.registry.BENCHMARKS`; a backbone's
own benchmarks (3DGS: `raster`) come through the `mono_hdr.benchmarks` entry-point group.
"""

from mono_hdr_plugin.apps.bench import cost, curves, paper  # noqa: F401 - registers "cost", "curves" and "paper"
