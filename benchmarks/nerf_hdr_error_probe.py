"""Where a run's HDR error lives on a scene with a tiny, very bright source: the source's
brightness against the room, or the room itself.

    python benchmarks/nerf_hdr_error_probe.py --scene lamp-room --methods mono hdr-nerf --steps 1500
    python benchmarks/nerf_hdr_error_probe.py --methods mono --set backbone.field.color_activation=sigmoid

Own-max HDR PSNR divides each image by its own maximum, so on lamp-room (a 3000-unit bulb in a
room of ~0.5) the bulb's peak sets the scale of every other pixel: a peak that is half as bright
as it should be against the walls makes the whole room twice as bright after normalisation. The
probe trains each method for a fixed number of steps (rows comparable step for step), then
scores the test views:
- own-max HDR PSNR (the headline);
- peak ratio: (prediction max / prediction room median) over (GT max / GT room median), where
  the room is every pixel below 1 % of the GT max; 1 is right, < 1 means the source is too dim;
- room-matched PSNR: own-max PSNR after scaling the normalised prediction so that its room
  median equals the GT's (clamped to [0, 1] as the metric does): the error that is left once the
  source's brightness is right. A large gain over own-max says the deficit is the source's peak.
- room PSNR: own-max PSNR over the room pixels only;
- LDR PSNR at the training exposure.
Writes mu-law PNGs of the first test view (prediction and GT, own max) to --out.
"""

import json
import tempfile
from pathlib import Path

import torch

from mono_hdr_plugin.apps.bench import script_args as args_of
from mono_hdr_plugin.apps.bench.runs import RunBudget, RunSpec, build_run, cached_scene
from mono_hdr_plugin.core.metrics import mu_law, psnr, tone_mapped_pair
from mono_hdr_plugin.data.io import write_png

ROOM_FRACTION_OF_PEAK = 0.01


def error_split(pred_hdr: torch.Tensor, gt_hdr: torch.Tensor) -> dict[str, float]:
    """The figures of the module docstring for one view."""
    pred_hdr, gt_hdr = pred_hdr.double(), gt_hdr.double()
    pred, gt = tone_mapped_pair(pred_hdr, gt_hdr, "own_max")
    room = gt_hdr.max(dim=-1).values < ROOM_FRACTION_OF_PEAK * gt_hdr.max()
    pred_linear = (pred_hdr / pred_hdr.max().clamp_min(1e-12)).clamp(0, 1)
    gt_linear = gt_hdr / gt_hdr.max()
    pred_room, gt_room = pred_linear[room].median().clamp_min(1e-12), gt_linear[room].median()
    matched = mu_law((pred_linear * (gt_room / pred_room)).clamp(0, 1))
    return {
        "hdr_psnr": psnr(pred, gt),
        "peak_ratio": float(gt_room / pred_room),
        "room_matched_psnr": psnr(matched, gt),
        "room_psnr": psnr(pred[room], gt[room]),
        "room_share": float(room.double().mean()),
    }


def probe(
    method: str, scene_name: str, steps: int, out: Path, overrides: tuple = (), label: str = ""
) -> dict[str, float]:
    spec = RunSpec(backbone="nerf", method=method, scene=scene_name, overrides=overrides)
    scene = cached_scene(spec.scene, spec.exposure_index)
    trainer = build_run(spec, scene, Path(tempfile.mkdtemp()), RunBudget(steps=steps))
    trainer.fit([])
    pipeline, figures = trainer.pipeline, []
    views = [v for v in scene.test if v.hdr is not None and v.exposure in scene.train_exposures]
    with torch.no_grad(), pipeline.evaluating():
        for index, view in enumerate(views):
            frame = pipeline.render(view.camera, view.exposure)
            figures.append(error_split(frame.hdr, view.hdr) | {"ldr_psnr": psnr(frame.ldr, view.image)})
            if index == 0:
                pred, gt = tone_mapped_pair(frame.hdr, view.hdr, "own_max")
                write_png(out / f"{scene_name}_{method}_{steps}{label}_pred.png", pred.float().numpy())
                write_png(out / f"{scene_name}_{method}_{steps}_gt.png", gt.float().numpy())
    means = {key: sum(f[key] for f in figures) / len(figures) for key in figures[0]}
    return means | {"train_seconds": trainer.train_seconds}


def main() -> None:
    parser = args_of.script_parser(__doc__)
    args_of.add_scenes(parser, "lamp-room")
    args_of.add_methods(parser, ["mono", "hdr-nerf"])
    args_of.add_count(parser, "--steps", 1500)
    args_of.add_out(parser, Path("outputs/nerf_hdr_error_probe"))
    args_of.add_overrides(parser)
    args = parser.parse_args()
    overrides = args_of.overrides(args.set)
    args.out.mkdir(parents=True, exist_ok=True)
    label = "".join(f"_{key.rsplit('.', 1)[-1]}-{value}" for key, value in overrides)
    results = {}
    for method in args.methods:
        results[method] = probe(method, args.scene, args.steps, args.out, overrides, label)
        print(method, json.dumps({k: round(v, 3) for k, v in results[method].items()}), flush=True)
    (args.out / f"{args.scene}_{args.steps}{label}.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
