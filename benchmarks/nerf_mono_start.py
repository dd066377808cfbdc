"""Why Mono-HDR-NeRF started slower than HDR-NeRF on the grid field, measured.

    python benchmarks/nerf_mono_start.py --scene demo --steps 300 --every 50 \
        --out benchmarks/results/nerf_mono_start

Trains every method on the NeRF cpu field for the same number of steps, with the converters
(L2H-CC, H2L-CC, the baselines' CRF) at the official codes' 5e-4 ("official") and at the
backbone's converter_lr, the rate of the field's own MLPs ("field rate", the default now), plus
Mono-HDR without its HDR terms as the LDR reference. Evaluates HDR and LDR PSNR every `every`
steps. Counted in steps, with the CPU seconds beside them, so runs made on a busy machine stay
comparable; one recipe per row, the same for every method.
"""

import time
from pathlib import Path

import torch

from backbones.nerf import NerfBackbone
from mono_hdr_plugin.apps.bench import script_args as args_of
from mono_hdr_plugin.apps.bench.runs import cached_scene, run_facts
from mono_hdr_plugin.core.backbone import OFFICIAL_CONVERTER_LR
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.methods.base import MethodConfig
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.trainer import Trainer

VARIANTS = {  # name -> (method, MethodConfig overrides)
    "mono, official": ("mono", {"converter_lr": OFFICIAL_CONVERTER_LR}),
    "mono, field rate": ("mono", {}),
    "hdr-nerf, official": ("hdr-nerf", {"converter_lr": OFFICIAL_CONVERTER_LR}),
    "hdr-nerf, field rate": ("hdr-nerf", {}),
    "hdr-gs, official": ("hdr-gs", {"converter_lr": OFFICIAL_CONVERTER_LR}),
    "hdr-gs, field rate": ("hdr-gs", {}),
    "mono, LDR loss only": ("mono", {"use_hdr_loss": False, "use_h2l_loss": False}),
}


def run(variant: str, scene_name: str, steps: int, every: int, eval_views: int, out: Path, seed: int) -> dict:
    method, overrides = VARIANTS[variant]
    scene = cached_scene(scene_name, 1)
    config = train_config_for(type(NerfBackbone.presets()["cpu"]))(
        backbone=NerfBackbone.presets()["cpu"],
        max_steps=steps,
        out=out / "run",
        quiet=True,
        save_renders=False,
        checkpoint_every=10**9,
        max_eval_views=eval_views,
        seed=seed,
        data=DataConfig(scene=scene_name),
        hdr=MethodConfig(method=method, **overrides),
    )
    trainer = Trainer(config, "nerf", scene)
    converter_lr = next(g["lr"] for g in trainer.optimizer.param_groups if g["name"] == "method")
    curve, cpu_seconds = [], 0.0
    while trainer.step < steps:
        started = time.process_time()
        trainer.train_step()
        cpu_seconds += time.process_time() - started
        if trainer.step % every == 0:
            metrics = trainer.evaluate()
            curve.append(
                {
                    "step": trainer.step,
                    "cpu_seconds": cpu_seconds,
                    "train_seconds": trainer.train_seconds,
                    **{key: metrics[key] for key in ("hdr_psnr", "hdr_psnr_gt_max", "ldr_psnr")},
                }
            )
            print(
                f"{variant:<22} step {trainer.step:>5}  HDR {metrics['hdr_psnr']:6.2f}  LDR {metrics['ldr_psnr']:6.2f}",
                flush=True,
            )
    return {"variant": variant, "method": method, "converter_lr": converter_lr, "curve": curve}


def markdown(results: dict) -> str:
    steps = [point["step"] for point in results["runs"][0]["curve"]]
    header = " | ".join(f"step {s}" for s in steps)
    lines = [
        f"Scene `{results['scene']}`, t3, NeRF preset cpu, {results['eval_views']} test views, seed "
        f"{results['seed']}; HDR / LDR PSNR (dB) after each number of steps; git "
        f"{results['facts']['git_commit'][:10]}.",
        "",
        f"| variant | converter lr | {header} | CPU s |",
        "|---|---|" + "---|" * len(steps) + "---|",
    ]
    for row in results["runs"]:
        cells = " | ".join(f"{p['hdr_psnr']:.2f} / {p['ldr_psnr']:.2f}" for p in row["curve"])
        lines.append(
            f"| {row['variant']} | {row['converter_lr']:g} | {cells} | {row['curve'][-1]['cpu_seconds']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = args_of.script_parser(__doc__)
    args_of.add_scenes(parser, "demo")
    args_of.add_count(parser, "--steps", 300)
    args_of.add_count(parser, "--every", 50, "steps between evaluations")
    args_of.add_count(parser, "--eval-views", 8, "test views per evaluation")
    parser.add_argument("--seed", type=int, default=0)
    args_of.add_threads(parser)
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    args_of.add_out(parser, Path("benchmarks/results/nerf_mono_start"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    results = {
        "facts": run_facts(),
        "scene": args.scene,
        "steps": args.steps,
        "eval_views": args.eval_views,
        "seed": args.seed,
        "runs": [],
    }
    for variant in args.variants:
        results["runs"].append(run(variant, args.scene, args.steps, args.every, args.eval_views, args.out, args.seed))
        write_json(args.out / "results.json", results)
        (args.out / "results.md").write_text(markdown(results))
    print(markdown(results))


if __name__ == "__main__":
    main()
