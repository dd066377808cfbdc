"""Table of the --hdr-prior-weight runs of benchmarks/run_hdr_prior_weight.sh: OUT/<weight>/<scene>/metrics.json
-> OUT/weight.json and OUT/weight.md. The weight with the best mean GT-max HDR PSNR over the scenes of --choose
is marked; the --confirm scenes are listed apart (they took no part in the choice)."""

import argparse
import json
import math
from pathlib import Path

from mono_hdr_plugin.data.io import write_json

KEYS = (
    "hdr_psnr_gt_max",
    "hdr_psnr_unclipped",
    "hdr_psnr_clipped",
    "hdr_psnr",
    "ldr_psnr",
    "hdr_rank_correlation_g",
    "hdr_log_slope_r",
    "hdr_log_slope_g",
    "hdr_log_slope_b",
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--choose", nargs="+", required=True)
    parser.add_argument("--confirm", nargs="+", required=True)
    args = parser.parse_args()
    weights = sorted((p.name for p in args.out.iterdir() if p.is_dir()), key=float)
    rows = {
        weight: {
            scene: {key: json.loads((args.out / weight / scene / "metrics.json").read_text()).get(key) for key in KEYS}
            for scene in args.choose + args.confirm
        }
        for weight in weights
    }
    mean = {w: sum(rows[w][s]["hdr_psnr_gt_max"] for s in args.choose) / len(args.choose) for w in weights}
    chosen = max(weights, key=lambda w: mean[w])
    write_json(args.out / "weight.json", {"rows": rows, "mean_gt_max_on_choose": mean, "chosen": chosen})
    lines = [
        "# --hdr-prior-weight: Mono-HDR-GS without HDR views, t3, 1000 steps, seed 0",
        "",
        "Written by `bash benchmarks/run_hdr_prior_weight.sh`. HDR PSNR in dB (GT-max; unclipped and clipped",
        "pixels apart; own-max), LDR PSNR, and the radiance-consistency scores against the linearised test photo.",
        f"Chosen on {', '.join(args.choose)} (mean GT-max): **{chosen}**; confirmed on {', '.join(args.confirm)}.",
        "",
        "| weight | scene | GT-max | unclipped | clipped | own-max | LDR | rank g | slope r / g / b |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def cell(value) -> str:
        return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.2f}"

    for scene in args.choose + args.confirm:
        for weight in weights:
            r = rows[weight][scene]
            slopes = " / ".join(cell(r[f"hdr_log_slope_{c}"]) for c in "rgb")
            lines.append(
                f"| {weight} | {scene}{' (confirm)' if scene in args.confirm else ''} | {cell(r['hdr_psnr_gt_max'])} "
                f"| {cell(r['hdr_psnr_unclipped'])} | {cell(r['hdr_psnr_clipped'])} | {cell(r['hdr_psnr'])} "
                f"| {cell(r['ldr_psnr'])} | {cell(r['hdr_rank_correlation_g'])} | {slopes} |"
            )
    (args.out / "weight.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
