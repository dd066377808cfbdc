"""Quality against training seconds on a real capture (a `process-data` folder), one Mono-HDR-GS run
per training recipe: whole images, region training (--region-pixels), the pyramid, both. Held-out
views as the capture's protocol gives them (every 8th photo); a real capture has no HDR ground truth,
so the curves are held-out LDR PSNR / SSIM. Each run trains in this process, one after another;
finished runs are kept in OUT/curves.json (the script resumes). Run it with nothing else on the machine:

    python benchmarks/region_curves_real.py --data /tmp/mono-hdr-lund/data --downscale 1 \\
        --seconds 450 --out benchmarks/results/regions/lund_1024
"""

import json
from pathlib import Path
from typing import Any

import torch

from backbones.gs import GaussianBackbone
from mono_hdr_plugin.apps.bench import script_args as args_of
from mono_hdr_plugin.apps.bench.runs import EvaluateAlong, peak_memory_mib, reset_peak_memory
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.trainer import Trainer

RECIPES: dict[str, dict[str, Any]] = {
    "whole": {"pyramid_levels": 1, "region_pixels": None},
    "regions": {"pyramid_levels": 1, "region_pixels": 16384},
    "pyramid": {"pyramid_levels": 3, "region_pixels": None},
    "pyramid+regions": {"pyramid_levels": 3, "region_pixels": 16384},
}
"""Each run's training recipe: the TrainConfig fields it sets on top of the cpu preset."""


def run_recipe(name: str, data: DataConfig, seconds: float, points: int, out: Path) -> dict[str, Any]:
    scene = load_scene(data)
    reset_peak_memory()
    config = train_config_for(GaussianBackbone.config_class)(
        backbone=GaussianBackbone.presets()["cpu"],
        data=data,
        max_seconds=seconds,
        out=out / "runs" / name,
        quiet=True,
        save_renders=False,
        checkpoint_every=10**9,
        seed=0,
        **RECIPES[name],
    )
    trainer = Trainer(config, "gs", scene)
    curve = EvaluateAlong(points)
    trainer.fit([curve])
    return {
        "recipe": RECIPES[name],
        "curve": curve.curve,
        "steps": trainer.step,
        "gaussians": trainer.backbone.num_gaussians,
        "peak_memory_mib": peak_memory_mib(),
        "view_size": [scene.train[0].camera.width, scene.train[0].camera.height],
    }


def report(rows: dict[str, dict[str, Any]]) -> str:
    lines = [
        "| recipe | steps | held-out LDR PSNR along the run (s: dB) | final LDR PSNR / SSIM | Gaussians | peak MiB |",
        "|---|---|---|---|---|---|",
    ]
    for name, row in rows.items():
        along = " / ".join(f"{point['train_seconds']:.0f}: {point['ldr_psnr']:.2f}" for point in row["curve"])
        final = row["curve"][-1]
        lines.append(
            f"| {name} | {row['steps']} | {along} | {final['ldr_psnr']:.2f} / {final['ldr_ssim']:.3f} | "
            f"{row['gaussians']:,} | {row['peak_memory_mib']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def plot(rows: dict[str, dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(10, 4))
    for name, row in rows.items():
        seconds = [point["train_seconds"] for point in row["curve"]]
        for axis, key in zip(axes, ("ldr_psnr", "ldr_ssim"), strict=True):
            axis.plot(seconds, [point[key] for point in row["curve"]], marker="o", label=name)
    for axis, label in zip(axes, ("held-out LDR PSNR (dB)", "held-out LDR SSIM"), strict=True):
        axis.set_xlabel("training seconds")
        axis.set_ylabel(label)
        axis.grid(alpha=0.3)
    axes[0].legend()
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def main() -> None:
    parser = args_of.script_parser(__doc__)
    parser.add_argument("--data", type=Path, required=True, help="a process-data folder (or any --data layout)")
    args_of.add_count(parser, "--downscale", 1, "train on the photos shrunk by this factor")
    parser.add_argument("--seconds", type=float, default=450.0, help="training seconds per run")
    args_of.add_count(parser, "--points", 5, "evaluations along each run")
    parser.add_argument("--recipes", nargs="+", choices=list(RECIPES), default=list(RECIPES))
    parser.add_argument("--out", type=Path, required=True, help="folder for curves.json, curves.md, curves.png")
    args_of.add_threads(parser)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    store = args.out / "curves.json"
    rows = json.loads(store.read_text())["rows"] if store.is_file() else {}
    data = DataConfig(data=args.data, downscale=args.downscale)
    for name in args.recipes:
        if name not in rows:
            rows[name] = run_recipe(name, data, args.seconds, args.points, args.out)
            write_json(store, {"data": str(args.data), "downscale": args.downscale, "rows": rows})
            print(f"{name}: {rows[name]['curve'][-1]['ldr_psnr']:.2f} dB after {rows[name]['steps']} steps")
    (args.out / "curves.md").write_text(report(rows))
    plot(rows, args.out / "curves.png")
    print(report(rows))


if __name__ == "__main__":
    main()
