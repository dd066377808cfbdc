"""Sweep of the 3DGS CPU recipe: quality after a fixed number of steps, and CPU time per step.

On a shared machine wall-clock time is disturbed, so runs are compared at equal steps, with
one torch thread, and each records its own CPU time per step (process time): the figure
that decides how many steps fit in a budget. Every variant is a set of overrides of the cpu
preset; every variant runs on every scene given, with Mono-HDR and both baselines alike.

    python benchmarks/gs_cpu_sweep.py --scenes demo glossy --steps 3000 --eval-every 1000 \\
        --variant base --variant "lr_sh_dc=0.0025" --out benchmarks/results/gs_cpu_sweep
"""

import copy
import json
import os
import time
from pathlib import Path

import torch

from backbones.gs import GaussianBackbone
from mono_hdr_plugin.apps.bench import script_args as args_of
from mono_hdr_plugin.apps.bench.runs import set_override
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.trainer import Trainer


def configured(preset: str, overrides: tuple[tuple[str, object], ...]):
    config = copy.deepcopy(GaussianBackbone.presets()[preset])
    for path, value in overrides:
        set_override(config, path, value)
    return config


def run(
    scene_name: str,
    method: str,
    preset: str,
    overrides: tuple,
    steps: int,
    eval_every: int,
    eval_views: int,
    out: Path,
    seed: int = 0,
) -> dict:
    scene = load_scene(DataConfig(scene=scene_name))
    backbone = configured(preset, overrides)
    config = train_config_for(type(backbone), method)(
        backbone=backbone,
        preset=preset,
        out=out,
        quiet=True,
        max_steps=steps,
        save_renders=False,
        checkpoint_every=10**9,
        max_eval_views=eval_views,
        seed=seed,
    )
    trainer = Trainer(config, "gs", scene)
    curve, cpu = [], 0.0
    while trainer.step < steps:
        started = time.process_time()
        trainer.train_step()
        cpu += time.process_time() - started
        if trainer.step % eval_every == 0 or trainer.step == steps:
            metrics = trainer.evaluate()
            curve.append(
                {
                    "steps": trainer.step,
                    "cpu_seconds": cpu,
                    "gaussians": trainer.backbone.num_gaussians,
                    **{k: metrics[k] for k in ("hdr_psnr", "hdr_psnr_gt_max", "hdr_ssim", "ldr_psnr", "ldr_ssim")},
                }
            )
            print(scene_name, method, curve[-1], flush=True)
    return {
        "scene": scene_name,
        "method": method,
        "preset": preset,
        "overrides": dict(overrides),
        "curve": curve,
        "cpu_ms_per_step": 1000 * cpu / steps,
    }


def main() -> None:
    parser = args_of.script_parser(__doc__)
    args_of.add_scenes(parser, ["demo"])
    args_of.add_methods(parser, ["mono"])
    parser.add_argument("--preset", default="cpu")
    args_of.add_variants(parser, "lr_sh_dc=0.0025")
    args_of.add_count(parser, "--steps", 3000)
    args_of.add_count(parser, "--eval-every", 1000, "steps between evaluations")
    args_of.add_count(parser, "--eval-views", 6, "test views per evaluation")
    args_of.add_out(parser, Path("benchmarks/results/gs_cpu_sweep"))
    parser.add_argument("--label", default="", help="stored with the results: the load they ran under")
    args = parser.parse_args()
    torch.set_num_threads(1)
    results_path = args.out / "sweep.json"
    results = json.loads(results_path.read_text()) if results_path.is_file() else {"runs": []}
    for name in args.variant or ["base"]:
        overrides = args_of.variant_overrides(name)
        for scene in args.scenes:
            for method in args.methods:
                record = run(
                    scene,
                    method,
                    args.preset,
                    overrides,
                    args.steps,
                    args.eval_every,
                    args.eval_views,
                    args.out / "runs",
                )
                record.update(
                    variant=name,
                    label=args.label,
                    load_average=os.getloadavg(),
                    date=time.strftime("%Y-%m-%d %H:%M:%S"),
                )
                results["runs"].append(record)
                write_json(results_path, results)


if __name__ == "__main__":
    main()
