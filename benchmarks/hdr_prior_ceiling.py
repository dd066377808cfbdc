"""What HDR a run without HDR views could reach at best: an oracle that knows the ground truth
wherever the photo records it and nothing where the photo clips.

    python benchmarks/hdr_prior_ceiling.py --out benchmarks/results/hdr_prior

The oracle's HDR is the ground truth, per channel, up to the exposure's clip level 1 / t (the
radiance at which the studio's photo at exposure t saturates) and held at that level above it:
exact on every value the photo records, and the least it can claim on values the photo clips
(a non-decreasing converter cannot put a clipped value below the brightest recorded one). Its
scores on each test view, at each single-protocol exposure t1, t3, t5, are therefore ceilings for
any method trained on those photos without HDR ground truth: own-max (the paper's score, set by
the brightest pixel), GT-max, and the clipped share of the pixels.
"""

import argparse
import json
from pathlib import Path

import torch

from mono_hdr_plugin.core.metrics import clipped_split_metrics, hdr_metrics
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.data.loading import load_scene

SCENES = ("demo", "lamp-room", "textured-desk", "glossy", "coloured-light", "sunlit-window")
EXPOSURE_INDICES = (0, 1, 2)
KEYS = ("hdr_psnr", "hdr_psnr_gt_max", "clipped_fraction")


def oracle_scores(scene_name: str, exposure_index: int) -> dict:
    scene = load_scene(DataConfig(scene=scene_name, exposure_index=exposure_index))
    rows = []
    for view in [v for v in scene.test if v.hdr is not None]:
        oracle = torch.minimum(view.hdr, torch.full_like(view.hdr, 1.0 / view.exposure))
        scores = hdr_metrics(oracle, view.hdr) | clipped_split_metrics(oracle, view.hdr, view.image)
        rows.append({"view": view.stem} | {key: scores[key] for key in KEYS})
    return {
        "scene": scene_name,
        "exposure": scene.test[0].exposure,
        "peak_over_clip": float(max(v.hdr.max() * v.exposure for v in scene.test if v.hdr is not None)),
        "views": rows,
        "range": {key: (min(r[key] for r in rows), max(r[key] for r in rows)) for key in KEYS},
    }


def markdown(results: list[dict]) -> str:
    lines = [
        "# Ceiling of HDR without HDR views (oracle exact where the photo records, clip level above)",
        "",
        "Written by `python benchmarks/hdr_prior_ceiling.py --out benchmarks/results/hdr_prior`; ranges over the",
        "scene's test views.",
        "",
        "| scene | exposure (s) | brightest / clip level | own-max dB | GT-max dB | clipped pixels |",
        "|---|---|---|---|---|---|",
    ]
    for row in results:
        own, gt, clipped = (row["range"][key] for key in KEYS)
        lines.append(
            f"| {row['scene']} | {row['exposure']:g} | {row['peak_over_clip']:.0f}x | {own[0]:.1f}-{own[1]:.1f} "
            f"| {gt[0]:.1f}-{gt[1]:.1f} | {100 * clipped[0]:.1f}-{100 * clipped[1]:.1f} % |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    args = parser.parse_args()
    results = [oracle_scores(name, index) for name in args.scenes for index in EXPOSURE_INDICES]
    write_json(args.out / "ceiling.json", results)
    (args.out / "ceiling.md").write_text(markdown(results))
    print(json.dumps([{k: r[k] for k in ("scene", "exposure", "range")} for r in results], indent=1))


if __name__ == "__main__":
    main()
