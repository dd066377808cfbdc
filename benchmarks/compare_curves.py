"""Two `mono-hdr bench curves` runs of the same rows (before and after a change) in one table and
one plot, the pair a change of the default training asks for:

    python benchmarks/compare_curves.py BEFORE/curves.json AFTER/curves.json \\
        --names "L2H-CC on the colour" "L2H-CC on the logit" --out benchmarks/results/nerf_l2h_input

Writes OUT/compare.md (each row's final figures under both runs, and after minus before) and
OUT/compare.png (HDR and LDR PSNR against training seconds, a row of panels per scene, a line per
run and row).
"""

import json
from pathlib import Path

from mono_hdr_plugin.apps.bench import script_args as args_of
from mono_hdr_plugin.apps.bench.curves import plot_curves
from mono_hdr_plugin.apps.bench.report import fmt, label


def finished_rows(path: Path) -> dict[tuple[str, str], dict]:
    rows = json.loads(path.read_text())["rows"].values()
    return {(row["spec"]["scene"], label(row["spec"])): row for row in rows if row["status"] == "ok"}


def comparison_table(runs: list[dict], names: list[str]) -> list[str]:
    columns = ["HDR PSNR", "HDR PSNR (GT max)", "LDR PSNR", "steps", "ms / step"]
    header = ["scene", "backbone / method"] + [f"{column}, {name}" for name in names for column in columns]
    header += ["HDR after - before", "LDR after - before"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for key in sorted(set(runs[0]) & set(runs[1])):
        cells = list(key)
        for run in runs:
            row = run[key]
            final = row["final"]
            cells += [
                fmt(final["hdr_psnr"]),
                fmt(final["hdr_psnr_gt_max"]),
                fmt(final["ldr_psnr"]),
                str(final["steps"]),
                f"{1000 * row['mean_step_seconds']:.1f}",
            ]
        before, after = runs[0][key]["final"], runs[1][key]["final"]
        cells += [f"{after['hdr_psnr'] - before['hdr_psnr']:+.2f}", f"{after['ldr_psnr'] - before['ldr_psnr']:+.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    parser = args_of.script_parser(__doc__)
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--names", nargs=2, default=["before", "after"])
    args_of.add_out(parser, None)
    args = parser.parse_args()
    runs = [finished_rows(args.before), finished_rows(args.after)]
    if not set(runs[0]) & set(runs[1]):
        raise SystemExit(f"{args.before} and {args.after} share no finished row (scene, backbone / method)")
    args.out.mkdir(parents=True, exist_ok=True)
    lines = comparison_table(runs, args.names)
    lines += [
        "",
        f"Made by `python benchmarks/compare_curves.py {args.before} {args.after} --names "
        f"{' '.join(repr(n) for n in args.names)} --out {args.out}`.",
    ]
    (args.out / "compare.md").write_text("\n".join(lines) + "\n")
    relabelled = []
    for name, run in zip(args.names, runs):
        for row in run.values():
            relabelled.append(row | {"spec": row["spec"] | {"method": f"{row['spec']['method']} ({name})"}})
    plot_curves(relabelled, args.out / "compare.png")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
