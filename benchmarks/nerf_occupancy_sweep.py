"""Quality per second of the NeRF cpu field under variants of its occupancy grid.

Each variant is a set of overrides of the cpu preset's field (`backbone.field.<name>`), run on
every scene and method given under the same time budget as `mono-hdr bench curves`, with
evaluations along the run, so variants are compared at equal training seconds. Run it with
nothing else on the machine:

    python benchmarks/nerf_occupancy_sweep.py --scenes demo lamp-room sunlit-window glossy coloured-light \\
        --methods mono --variant base --variant occupancy_threshold=0.001 --seconds 120 \\
        --out benchmarks/results/nerf_occupancy_sweep

Writes OUT/sweep.json (rows as `bench curves` stores them; an interrupted sweep resumes) and
OUT/sweep.md (HDR / LDR PSNR at each evaluation, step time, share of seen cells kept at the end).
"""

import sys
from pathlib import Path

from mono_hdr_plugin.apps.bench import script_args as args_of
from mono_hdr_plugin.apps.bench.runs import ExecutorConfig, RowStore, RunBudget, RunSpec, execute


def variant_name(spec: dict) -> str:
    return ",".join(f"{path.rsplit('.', 1)[1]}={value}" for path, value in spec["overrides"]) or "base"


def write_report(store: RowStore, path: Path) -> None:
    rows = sorted(
        (row for row in store.rows.values() if row["status"] == "ok"),
        key=lambda r: (r["spec"]["scene"], r["spec"]["method"], variant_name(r["spec"])),
    )
    points = max((len(row["curve"]) for row in rows), default=0)
    times = [f"{row['curve'][i]['train_seconds']:.0f} s" for row in rows[:1] for i in range(points)]
    lines = [
        "HDR / LDR PSNR (dB) at each evaluation; ms a step over the run; share of seen cells occupied at the end.",
        "",
        "| scene | method | variant | " + " | ".join(times) + " | ms / step | occupied |",
        "|---|---|---|" + "---|" * points + "---|---|",
    ]
    for row in rows:
        cells = " | ".join(f"{c['hdr_psnr']:.1f} / {c['ldr_psnr']:.1f}" for c in row["curve"])
        occupied = row["backbone_statistics"].get("occupied_fraction")
        lines.append(
            f"| {row['spec']['scene']} | {row['spec']['method']} | {variant_name(row['spec'])} | {cells} | "
            f"{1000 * row['mean_step_seconds']:.0f} | {'' if occupied is None else f'{100 * occupied:.0f} %'} |"
        )
    lines += [f"\nFailed: {row['key']}: {row['error']}" for row in store.rows.values() if row["status"] != "ok"]
    lines += ["", f"Made by `python {' '.join(sys.argv)}` (one seed; machine, commit and date in sweep.json)."]
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = args_of.script_parser(__doc__)
    args_of.add_scenes(parser, ["lamp-room"])
    args_of.add_methods(parser, ["mono"])
    args_of.add_variants(parser, "occupancy_threshold=0.001, fields of backbone.field")
    args_of.add_seconds(parser, 120.0)
    args_of.add_count(parser, "--eval-points", 3, "evaluations along each run")
    args_of.add_count(parser, "--eval-views", 8, "test views per evaluation")
    args_of.add_out(parser, Path("benchmarks/results/nerf_occupancy_sweep"))
    args = parser.parse_args()
    variants = [args_of.variant_overrides(text, "backbone.field.") for text in args.variant or ["base"]]
    specs = [
        RunSpec(backbone="nerf", method=method, scene=scene, overrides=overrides)
        for overrides in variants
        for scene in args.scenes
        for method in args.methods
    ]
    budget = RunBudget(seconds=args.seconds, eval_points=args.eval_points, max_eval_views=args.eval_views)
    store = RowStore(args.out / "sweep.json", {"budget": budget.__dict__})
    try:
        execute(
            specs,
            budget,
            store,
            args.out / "runs",
            ExecutorConfig(),
            on_row=lambda row: write_report(store, args.out / "sweep.md"),
        )
    finally:
        if store.rows:
            write_report(store, args.out / "sweep.md")


if __name__ == "__main__":
    main()
