"""The radiance calibration's two checks that `bench curves` cannot make, measured.

    python benchmarks/calibration.py --scene demo --out benchmarks/results/calibration

1. Units without HDR ground truth: a model trained on the photos alone (the training views' HDR
   ground truth removed, only the photos and their exposure times) is calibrated in exposure-time
   units; a test view's calibrated HDR is compared with a bracket merge of that view's own photos
   at every exposure the scene has (colour-hdri's merge, the sRGB response the studio's `demo`
   camera uses), as the median ratio over pixels the training-exposure photo exposes well.
2. The anchoring loss against the post-hoc fit: runs with ground truth and `--hdr-scale-anchor`
   0.5, beside the same runs without it (the paper's recipe, calibrated after the fact), read from
   OUT/curves_<backbone>/curves.json (`mono-hdr bench curves` with the same steps, seed and scene;
   fixed-step runs are deterministic). With the anchor the fitted scale should stay near 1
   (training itself sets the level); the scores say whether anchoring costs or gains anything.

Every run: one seed, exposure t3, the backbone's default preset, a fixed number of steps (STEPS:
about 100 s on the quiet 2-core machine; steps, so that the figures do not depend on its load),
`eval_points` evaluations along the run (the fitted scale at each is kept, to show it settles).
"""

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mono_hdr_plugin.apps.bench import script_args as args_of
from mono_hdr_plugin.apps.bench.runs import EvaluateAlong, RunBudget, RunSpec, build_run, cached_scene, run_facts
from mono_hdr_plugin.core.calibration import well_exposed
from mono_hdr_plugin.core.exposure import srgb_response
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.data.photos.brackets import merge_bracket

BACKBONES = ("gs", "nerf")
STEPS = {"gs": 2000, "nerf": 1200}
MERGE_VIEWS = 4
ANCHOR = 0.5


def median_ratio(prediction: torch.Tensor, reference: torch.Tensor, photo: torch.Tensor) -> float:
    """Median of prediction / reference over the positive values of pixels `photo` exposes well."""
    exposed = well_exposed(photo)
    a, b = prediction[exposed].double(), reference[exposed].double()
    usable = (a > 0) & (b > 0)
    return math.exp(float(np.median((torch.log(a[usable]) - torch.log(b[usable])).numpy())))


def photos_only(scene):
    """The scene with its training views' HDR ground truth removed."""
    return dataclasses.replace(scene, train=[dataclasses.replace(view, hdr=None) for view in scene.train])


def units_against_brackets(backbone: str, scene_name: str, budget: RunBudget, out: Path) -> dict[str, Any]:
    budget = dataclasses.replace(budget, steps=STEPS[backbone])
    scene = photos_only(cached_scene(scene_name, 1))
    trainer = build_run(RunSpec(backbone, scene=scene_name), scene, out / f"units_{backbone}", budget)
    curve = EvaluateAlong(budget.eval_points)
    trainer.fit([curve])
    trainer.calibrate()
    brackets = load_scene(DataConfig(scene=scene_name, protocol="multi"))  # every test view at every exposure
    views = []
    for view in [v for v in scene.test if v.hdr is not None][:MERGE_VIEWS]:
        shots = sorted((v for v in brackets.test if v.view_id == view.view_id), key=lambda v: v.exposure)
        merged = merge_bracket(
            [shot.image.numpy() for shot in shots], [shot.exposure for shot in shots], srgb_response(), [view.name]
        )
        with trainer.pipeline.evaluating():
            hdr = trainer.pipeline.render(view.camera, view.exposure).hdr
        views.append(
            {
                "view": view.stem,
                "exposures": [shot.exposure for shot in shots],
                "ratio_to_bracket_merge": median_ratio(hdr, torch.from_numpy(merged), view.image),
                "ratio_to_ground_truth": median_ratio(hdr, view.hdr, view.image),
                "merge_to_ground_truth": median_ratio(torch.from_numpy(merged), view.hdr, view.image),
            }
        )
    return {
        "backbone": backbone,
        "steps": trainer.step,
        "calibration": trainer.pipeline.calibration.state(),
        "scales_along_the_run": [point["radiance_scale"] for point in curve.curve],
        "views": views,
        "median_ratio_to_bracket_merge": float(np.median([v["ratio_to_bracket_merge"] for v in views])),
    }


def anchored_run(backbone: str, scene_name: str, anchor: float, budget: RunBudget, out: Path) -> dict[str, Any]:
    budget = dataclasses.replace(budget, steps=STEPS[backbone])
    spec = RunSpec(backbone, scene=scene_name, overrides=(("hdr.hdr_scale_anchor", anchor),))
    trainer = build_run(spec, cached_scene(scene_name, 1), out / f"anchor_{backbone}_{anchor:g}", budget)
    curve = EvaluateAlong(budget.eval_points)
    trainer.fit([curve])
    return {"backbone": backbone, "anchor": anchor, "steps": trainer.step, "curve": curve.curve}


def post_hoc_rows(out: Path, scene: str, backbones: list[str]) -> list[dict[str, Any]]:
    """The runs without the anchor, from `bench curves` in OUT/curves_<backbone> (none when absent)."""
    rows = []
    for backbone in backbones:
        path = out / f"curves_{backbone}" / "curves.json"
        if not path.is_file():
            continue
        for row in json.loads(path.read_text())["rows"].values():
            if row["status"] == "ok" and row["spec"]["scene"] == scene and not row["spec"]["overrides"]:
                final_steps = row["final"]["steps"]
                rows.append({"backbone": backbone, "anchor": 0.0, "steps": final_steps, "curve": row["curve"]})
    return rows


def write_report(results: dict[str, Any], path: Path) -> None:
    lines = [
        "# Radiance calibration: units without ground truth, and the anchoring loss",
        "",
        f"Scene `{results['scene']}`, t3, steps a run {results['steps']} (`{results['command']}`).",
        "",
        "## 1. Trained on photos only: calibrated HDR against a bracket merge of the same view",
        "",
        "| backbone | steps | units | scale | scales along the run | view | calibrated / merge "
        "| calibrated / GT | merge / GT |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in results["units"]:
        scales = ", ".join(f"{s:.4g}" for s in row["scales_along_the_run"])
        for view in row["views"]:
            lines.append(
                f"| {row['backbone']} | {row['steps']} | {row['calibration']['units']} | "
                f"{row['calibration']['scale']:.4g} | {scales} | {view['view']} | "
                f"{view['ratio_to_bracket_merge']:.3f} | {view['ratio_to_ground_truth']:.3f} | "
                f"{view['merge_to_ground_truth']:.3f} |"
            )
    lines += [
        "",
        "## 2. Anchoring loss (`--hdr-scale-anchor`) against the post-hoc fit alone",
        "",
        "| backbone | anchor | steps | scale | HDR PSNR own max | GT max | GT max, masked | median ratio | LDR PSNR |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in results["anchor"]:
        final = row["curve"][-1]
        lines.append(
            f"| {row['backbone']} | {row['anchor']:g} | {row['steps']} | {final['radiance_scale']:.4g} | "
            f"{final['hdr_psnr']:.2f} | {final['hdr_psnr_gt_max']:.2f} | {final['hdr_psnr_masked']:.2f} | "
            f"{final['hdr_median_ratio']:.3f} | {final['ldr_psnr']:.2f} |"
        )
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = args_of.script_parser(__doc__)
    args_of.add_out(parser, Path("benchmarks/results/calibration"))
    args_of.add_scenes(parser, "demo")
    parser.add_argument("--backbones", nargs="+", default=list(BACKBONES), choices=BACKBONES)
    args_of.add_count(parser, "--eval-points", 4, help="evaluations along each run")
    args_of.add_count(parser, "--max-eval-views", 8, help="test views per evaluation")
    args = parser.parse_args()
    budget = RunBudget(steps=1, eval_points=args.eval_points, max_eval_views=args.max_eval_views)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {
        "facts": run_facts(),
        "scene": args.scene,
        "steps": STEPS,
        "command": f"python benchmarks/calibration.py --scene {args.scene} --backbones {' '.join(args.backbones)}",
        "units": [units_against_brackets(b, args.scene, budget, out / "runs") for b in args.backbones],
        "anchor": [
            *post_hoc_rows(out, args.scene, args.backbones),
            *(anchored_run(b, args.scene, ANCHOR, budget, out / "runs") for b in args.backbones),
        ],
    }
    write_json(out / "calibration.json", results)
    write_report(results, out / "calibration.md")


if __name__ == "__main__":
    main()
