"""How much space the NeRF occupancy grid keeps along a run, beside the run's quality.

    python benchmarks/nerf_occupancy_probe.py --scene lamp-room --methods mono hdr-nerf --steps 1200
    python benchmarks/nerf_occupancy_probe.py --scene lamp-room --methods mono --threshold 0.001

Prints, every 200 steps, the fraction of seen cells marked occupied, and HDR / LDR PSNR (4 test
views) every 400 steps. Made to study why Mono-HDR-NeRF stalls on lamp-room (README, "What
accuracy costs in time"): at equal steps its grid keeps a quarter of the cells HDR-NeRF keeps.
"""

import tempfile
from pathlib import Path

from mono_hdr_plugin.apps.bench import script_args as args_of
from mono_hdr_plugin.apps.bench.runs import RunBudget, RunSpec, build_run, cached_scene
from mono_hdr_plugin.training.hooks import TrainingHook


class OccupancyAlong(TrainingHook):
    def __init__(self, every: int = 200, evaluate_every: int = 400):
        self.every, self.evaluate_every = every, evaluate_every

    def after_step(self, trainer, record) -> None:
        if trainer.step % self.every and not trainer.finished:
            return
        kept = trainer.backbone.statistics()["occupied_fraction"]
        metrics = trainer.evaluate() if trainer.step % self.evaluate_every == 0 or trainer.finished else {}
        psnr = "" if not metrics else f"  HDR {metrics['hdr_psnr']:.2f} dB  LDR {metrics['ldr_psnr']:.2f} dB"
        print(f"step {trainer.step:5d}  occupied {100 * kept:5.1f} % of seen cells{psnr}", flush=True)


def main() -> None:
    parser = args_of.script_parser(__doc__)
    args_of.add_scenes(parser, "lamp-room")
    args_of.add_methods(parser, ["mono", "hdr-nerf"])
    args_of.add_count(parser, "--steps", 1200)
    parser.add_argument("--threshold", type=float, default=None, help="occupancy_threshold (default: the preset's)")
    args = parser.parse_args()
    overrides = () if args.threshold is None else (("backbone.field.occupancy_threshold", args.threshold),)
    for method in args.methods:
        print(f"nerf / {method} on {args.scene}")
        spec = RunSpec(backbone="nerf", method=method, scene=args.scene, overrides=overrides)
        scene = cached_scene(spec.scene, spec.exposure_index)  # the exposure the benchmark rows train on
        trainer = build_run(spec, scene, Path(tempfile.mkdtemp()), RunBudget(steps=args.steps, max_eval_views=4))
        trainer.fit([OccupancyAlong()])


if __name__ == "__main__":
    main()
