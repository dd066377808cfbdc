"""`bench paper`'s figures from its rows, the orderings against the paper's, paper.md and the plots.

A variant's figure on a scene is the mean over seeds of its per-seed value (the mean over
exposures); the spread is the standard deviation over seeds. Averaged over scenes, a seed's value
is its mean over scenes and exposures. An ordering of two variants counts as REPRODUCED only when
it has the paper's sign and the gap between the means exceeds the sum of the two spreads; a gap
within the spreads is a TIE, and a gap beyond them the other way is REVERSED. With one seed there
is no spread, and the report says so.
"""

import itertools
import math
import statistics
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mono_hdr_plugin.apps.bench.paper_tables import Variant
from mono_hdr_plugin.apps.bench.report import fmt, pyplot
from mono_hdr_plugin.apps.bench.runs import RowStore, RunSpec

if TYPE_CHECKING:  # annotations only: paper imports this module
    from mono_hdr_plugin.apps.bench.paper import BenchPaperConfig

METRICS = ("hdr_psnr", "hdr_ssim", "hdr_psnr_gt_max", "ldr_psnr", "ldr_ssim")


# ----------------------------------------------------------------------------- aggregation
def seed_values(
    variant: Variant, store: RowStore, exposures: tuple[int, ...], metric: str, scenes: tuple[str, ...] | None = None
) -> dict[int, float]:
    """seed -> the metric averaged over `scenes` (default: the variant's) and the exposures; seeds
    with a failed or missing run are left out."""
    values = {}
    for seed in variant.seeds:
        runs = [
            store.rows.get(RunSpec(**{**variant.spec.__dict__, "scene": s, "exposure_index": e, "seed": seed}).key)
            for s in (scenes or variant.scenes)
            for e in exposures
        ]
        finished = [r for r in runs if r is not None and r["status"] == "ok" and r["final"][metric] is not None]
        if runs and len(finished) == len(runs):
            values[seed] = statistics.fmean(r["final"][metric] for r in finished)
    return values


def mean_spread(values: dict[int, float]) -> tuple[float | None, float | None]:
    """Mean and standard deviation over seeds (spread 0 with one seed, None with none)."""
    if not values:
        return None, None
    numbers = list(values.values())
    return statistics.fmean(numbers), statistics.stdev(numbers) if len(numbers) > 1 else 0.0


def ordering(ours_a: tuple[float, float], ours_b: tuple[float, float], paper_a: float, paper_b: float) -> str:
    """reproduced / tie / reversed, by the rule in this module's docstring."""
    (mean_a, spread_a), (mean_b, spread_b) = ours_a, ours_b
    gap = mean_a - mean_b
    if abs(gap) <= spread_a + spread_b:
        return "tie"
    return "reproduced" if (gap > 0) == (paper_a > paper_b) else "reversed"


def summarise(variants: list[Variant], store: RowStore, exposures: tuple[int, ...]) -> list[dict[str, Any]]:
    """Per variant: mean +- spread of each metric averaged over its scenes, and per scene HDR PSNR."""
    rows = []
    for variant in variants:
        row: dict[str, Any] = {
            "table": variant.table,
            "variant": variant.name,
            "backbone": variant.spec.backbone,
            "paper_hdr_psnr": variant.paper_hdr_psnr,
            "paper_ldr_psnr": variant.paper_ldr_psnr,
            "seeds": len(variant.seeds),
            "scenes": list(variant.scenes),
        }
        for metric in METRICS:
            row[metric] = mean_spread(seed_values(variant, store, exposures, metric))
        row["per_scene_hdr_psnr"] = {
            scene: mean_spread(seed_values(variant, store, exposures, "hdr_psnr", (scene,))) for scene in variant.scenes
        }
        rows.append(row)
    return rows


def orderings(rows: list[dict[str, Any]]) -> list[tuple[str, str, str]]:
    """(a, b, verdict) for every pair of rows of one table that both have a paper figure and a result."""
    usable = [r for r in rows if r["paper_hdr_psnr"] is not None and r["hdr_psnr"][0] is not None]
    verdicts = []
    for a, b in itertools.combinations(usable, 2):
        if a["paper_hdr_psnr"] != b["paper_hdr_psnr"]:
            verdicts.append(
                (
                    a["variant"],
                    b["variant"],
                    ordering(a["hdr_psnr"], b["hdr_psnr"], a["paper_hdr_psnr"], b["paper_hdr_psnr"]),
                )
            )
    return verdicts


# ---------------------------------------------------------------------------------- report
def _pm(value: tuple[float | None, float | None], digits: int = 2) -> str:
    mean, spread = value
    return "n/a" if mean is None else f"{mean:.{digits}f} +- {spread:.{digits}f}"


def write_paper_report(config: "BenchPaperConfig", variants: list[Variant], recipes: dict, store: RowStore) -> None:
    exposures = config.exposure_indices
    rows = summarise(variants, store, exposures)
    budget = store.settings["budget"]
    lines = [
        f"git {store.facts['git_commit'][:10]}; budget per run: "
        f"{fmt(budget['seconds'], 0)} s / {budget['steps'] or '-'} steps; "
        f"{config.resolution or 128} x {config.resolution or 128} px; exposures "
        f"{', '.join(f't{2 * e + 1}' for e in exposures)} averaged; mean +- standard deviation over seeds. "
        "An ordering is reproduced when its sign matches the paper's and the gap exceeds the sum of "
        "the two spreads (tie: within them; reversed: beyond them, the other way).",
        "",
    ]
    for table in dict.fromkeys(v.table for v in variants):
        table_rows = [r for r in rows if r["table"] == table]
        scenes = table_rows[0]["scenes"]
        lines += [
            f"### {table} (scenes: {', '.join(scenes)}; {table_rows[0]['seeds']} seed(s))",
            "",
            "| variant | HDR PSNR | paper HDR PSNR | HDR PSNR (GT max) | HDR SSIM | LDR PSNR | LDR SSIM | "
            + " | ".join(f"HDR PSNR {s}" for s in scenes)
            + " |",
            "|---" * (7 + len(scenes)) + "|",
        ]
        for r in table_rows:
            lines.append(
                f"| {r['variant']} | {_pm(r['hdr_psnr'])} | {fmt(r['paper_hdr_psnr'])} | "
                f"{_pm(r['hdr_psnr_gt_max'])} | {_pm(r['hdr_ssim'], 3)} | {_pm(r['ldr_psnr'])} | "
                f"{_pm(r['ldr_ssim'], 3)} | " + " | ".join(_pm(r["per_scene_hdr_psnr"][s]) for s in scenes) + " |"
            )
        verdicts = orderings(table_rows)
        counts = {v: sum(1 for *_, verdict in verdicts if verdict == v) for v in ("reproduced", "tie", "reversed")}
        lines += [
            "",
            f"Orderings against the paper's: {counts['reproduced']} reproduced, {counts['tie']} ties, "
            f"{counts['reversed']} reversed of {len(verdicts)} pairs.",
        ]
        lines += [f"- {a} vs {b}: {verdict}" for a, b, verdict in verdicts if verdict != "reproduced"]
        lines.append("")
    if recipes:
        lines += recipe_lines(config, variants, recipes, store)
    failed = [row for row in store.rows.values() if row["status"] != "ok"]
    lines += [f"Failed run {row['key']}: {row['error']}" for row in failed]
    config.out.mkdir(parents=True, exist_ok=True)
    (config.out / "paper.md").write_text("\n".join(lines) + "\n")
    table1 = [r for r in rows if r["table"] == "table1"]
    if table1 and any(r["hdr_psnr"][0] is not None for r in table1):
        plot_table1(table1, config.out / "paper_table1.png")
        plot_table1_curves(
            [v for v in variants if v.table == "table1"], store, exposures, config.out / "paper_curves.png"
        )


def recipe_lines(config: "BenchPaperConfig", variants: list[Variant], recipes: dict, store: RowStore) -> list[str]:
    """Shared CPU recipe against each method's own tuned recipe, on the scenes it was NOT tuned on."""
    exposures = config.exposure_indices
    report_scenes = tuple(s for s in config.scenes if s != config.tune_scene)
    lines = [
        f"### recipes: shared CPU recipe vs each method's own best (tuned on {config.tune_scene}, "
        f"reported on {', '.join(report_scenes)})",
        "",
        "| backbone method | trials | tuned settings | HDR PSNR shared | HDR PSNR own | LDR PSNR shared | "
        "LDR PSNR own |",
        "|---|---|---|---|---|---|---|",
    ]
    table1 = {v.name: v for v in variants if v.table == "table1"}
    for (row, method), recipe in recipes.items():
        shared = table1.get(f"{row} {method}")
        tuned = Variant("recipes", "", recipe["spec"], seeds=config.seeds, scenes=report_scenes)
        cells = []
        for metric in ("hdr_psnr", "ldr_psnr"):
            cells.append(
                _pm(mean_spread(seed_values(shared, store, exposures, metric, report_scenes))) if shared else "n/a"
            )
            cells.append(_pm(mean_spread(seed_values(tuned, store, exposures, metric))))
        settings = ", ".join(f"{path}={value:g}" for path, value in recipe["overrides"].items())
        lines.append(
            f"| {row} {method} | {recipe['trials']} | {settings} | {cells[0]} | {cells[1]} | {cells[2]} | {cells[3]} |"
        )
    return lines + [""]


def plot_table1(rows: list[dict], path: Path) -> None:
    """Bars of HDR and LDR PSNR (mean over scenes, error bars: spread over seeds), paper figures as markers."""
    plt = pyplot()
    figure, axes = plt.subplots(1, 2, figsize=(10, 4))
    names = [r["variant"] for r in rows]
    for axis, metric, paper_key, title in (
        (axes[0], "hdr_psnr", "paper_hdr_psnr", "HDR PSNR (dB, mu-law, own max)"),
        (axes[1], "ldr_psnr", "paper_ldr_psnr", "LDR PSNR (dB)"),
    ):
        means = [r[metric][0] if r[metric][0] is not None else math.nan for r in rows]
        spreads = [r[metric][1] or 0.0 for r in rows]
        axis.bar(range(len(rows)), means, yerr=spreads, capsize=4, color="#4c72b0", label="this code")
        axis.scatter(
            range(len(rows)),
            [r[paper_key] for r in rows],
            color="#dd8452",
            marker="D",
            zorder=3,
            label="paper (GPU, 30k / 200k steps)",
        )
        axis.set_xticks(range(len(rows)), names, rotation=20, fontsize=8)
        axis.set_title(title)
        axis.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def plot_table1_curves(variants: list[Variant], store: RowStore, exposures: tuple[int, ...], path: Path) -> None:
    """HDR PSNR against training seconds of every Table 1 row, averaged point by point over its runs."""
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(6.5, 4))
    for variant in variants:
        curves = [
            store.rows[s.key]["curve"]
            for s in variant.runs(exposures)
            if store.rows.get(s.key, {}).get("status") == "ok"
        ]
        if not curves:
            continue
        length = min(len(c) for c in curves)
        seconds = [statistics.fmean(c[i]["train_seconds"] for c in curves) for i in range(length)]
        hdr = [statistics.fmean(c[i]["hdr_psnr"] for c in curves) for i in range(length)]
        axis.plot(seconds, hdr, marker="o", label=variant.name)
    axis.set_xlabel("training seconds")
    axis.set_ylabel("HDR PSNR (dB)")
    axis.set_title("Table 1 rows: HDR PSNR against training time")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
