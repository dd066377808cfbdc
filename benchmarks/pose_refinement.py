"""Camera pose refinement (--camera-opt) on a studio scene whose training poses are perturbed by a known amount.

Three runs of one backbone on one scene, the same steps and seed: the exact poses ("clean"), the
perturbed poses without refinement ("perturbed") and with it ("refined"). Each training view's pose
is rotated by DEG degrees about a random axis through its centre and moved by FRACTION of the scene
radius (SceneInfo.extent, the radius of the camera rig) in a random direction, seeded. Held-out views
keep their exact poses, and are scored two ways: at those poses (nerfstudio's protocol), and with
their pose, exposure and white balance fitted on the left half of each photo and the right half
scored (BARF's protocol, --eval-pose on: refinement may move the whole world a little, and a pose
given in the old world is then a little off). Written: OUT/<backbone>.json and OUT/<backbone>.md
(held-out PSNR both ways, the share of the lost PSNR recovered, and the pose errors against the truth
before and after refinement, with the gauge freedom removed two ways: a similarity fit of the camera
centres, and a fit of whole poses, the rotation from the cameras' orientations).

    python benchmarks/pose_refinement.py --backbone gs --scene demo --steps 1000 --perturb-poses 1,0.01
"""

import argparse
import dataclasses
import math
import sys
import tempfile
import time
from pathlib import Path

import torch

from mono_hdr_plugin.core.camera_optimizer import CameraOptConfig, rotation_angle_degrees, so3_exp
from mono_hdr_plugin.core.registry import get_backbone
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.trainer import Trainer


def parse_perturbation(text: str) -> tuple[float, float]:
    """'DEG,FRACTION' -> (degrees, fraction of the scene radius)."""
    degrees, fraction = (float(part) for part in text.split(","))
    return degrees, fraction


def perturb_poses(scene: SceneData, degrees: float, fraction: float, seed: int) -> SceneData:
    """The scene with every training pose rotated by `degrees` about a random axis through its centre
    and moved by `fraction` of the scene radius in a random direction (both seeded); test views as they were."""
    generator = torch.Generator().manual_seed(seed)
    radius = scene.scene_info().extent
    train = []
    for view in scene.train:
        axis = torch.randn(3, generator=generator, dtype=torch.float64)
        direction = torch.randn(3, generator=generator, dtype=torch.float64)
        c2w = view.camera.c2w.double().clone()
        c2w[:3, :3] = so3_exp(axis / axis.norm() * math.radians(degrees)) @ c2w[:3, :3]
        c2w[:3, 3] += direction / direction.norm() * fraction * radius
        train.append(dataclasses.replace(view, camera=dataclasses.replace(view.camera, c2w=c2w.float())))
    return dataclasses.replace(scene, train=train)


def similarity_fit(source: torch.Tensor, target: torch.Tensor) -> tuple[float, torch.Tensor, torch.Tensor]:
    """Scale s, rotation R and translation t minimising |s R source + t - target|^2 over points [N, 3] (Umeyama)."""
    mean_s, mean_t = source.mean(0), target.mean(0)
    a, b = source - mean_s, target - mean_t
    u, singular, vt = torch.linalg.svd(b.T @ a / len(source))
    sign = torch.ones(3, dtype=source.dtype)
    sign[2] = torch.sign(torch.det(u @ vt))
    rotation = u @ torch.diag(sign) @ vt
    scale = float((singular * sign).sum() / a.square().sum(-1).mean())
    return scale, rotation, mean_t - scale * rotation @ mean_s


def orientation_fit(poses: list[torch.Tensor], truth: list[torch.Tensor]) -> tuple[float, torch.Tensor, torch.Tensor]:
    """The similarity (s, R, t) that best maps camera-to-world `poses` onto `truth` [4, 4] as whole
    poses: R the rotation nearest the sum of R_true R_pose^T (chordal mean of the orientations), then
    s and t fitting the centres by least squares with R fixed."""
    total = sum(true[:3, :3] @ pose[:3, :3].T for pose, true in zip(poses, truth, strict=True))
    u, _, vt = torch.linalg.svd(total)
    sign = torch.ones(3, dtype=total.dtype)
    sign[2] = torch.sign(torch.det(u @ vt))
    rotation = u @ torch.diag(sign) @ vt
    source = torch.stack([pose[:3, 3] for pose in poses]) @ rotation.T
    target = torch.stack([true[:3, 3] for true in truth])
    a, b = source - source.mean(0), target - target.mean(0)
    scale = float((a * b).sum() / a.square().sum())
    return scale, rotation, target.mean(0) - scale * source.mean(0)


def pose_errors(
    poses: list[torch.Tensor], truth: list[torch.Tensor], radius: float, gauge: str = "centres"
) -> dict[str, float]:
    """Rotation (degrees) and centre (fraction of the scene radius) errors of camera-to-world poses
    against the truth, after the similarity that best maps them onto the true ones: their centres
    (gauge "centres", Umeyama) or whole poses (gauge "poses", `orientation_fit`)."""
    poses64, truth64 = [p.double() for p in poses], [t.double() for t in truth]
    if gauge == "poses":
        scale, rotation, translation = orientation_fit(poses64, truth64)
    else:
        scale, rotation, translation = similarity_fit(
            torch.stack([p[:3, 3] for p in poses64]), torch.stack([t[:3, 3] for t in truth64])
        )
    rotations, centres = [], []
    for pose, true in zip(poses64, truth64, strict=True):
        aligned_rotation = rotation @ pose[:3, :3]
        aligned_centre = scale * rotation @ pose[:3, 3] + translation
        rotations.append(rotation_angle_degrees(true[:3, :3].T @ aligned_rotation))
        centres.append(float((aligned_centre - true[:3, 3]).norm()) / radius)
    return {
        "rotation_degrees_mean": sum(rotations) / len(rotations),
        "rotation_degrees_median": sorted(rotations)[len(rotations) // 2],
        "rotation_degrees_max": max(rotations),
        "translation_radius_mean": sum(centres) / len(centres),
        "translation_radius_max": max(centres),
        "alignment_scale": scale,
        "alignment_rotation_degrees": rotation_angle_degrees(rotation),
    }


def train_run(
    backbone: str, scene: SceneData, steps: int, seed: int, camera: CameraOptConfig, out: Path
) -> tuple[Trainer, dict]:
    """Train `backbone` (its default preset) on `scene` quietly and score the held-out views."""
    backbone_config = next(iter(get_backbone(backbone).presets().values()))
    config = train_config_for(type(backbone_config))(
        backbone=backbone_config,
        out=out,
        max_steps=steps,
        seed=seed,
        camera=dataclasses.replace(camera, eval_pose="on"),
        quiet=True,
        save_renders=False,
        checkpoint_every=10**9,
    )
    trainer = Trainer(config, backbone, scene)
    started = time.perf_counter()
    trainer.fit()
    metrics = trainer.evaluate()
    metrics["wall_seconds"] = time.perf_counter() - started
    return trainer, metrics


SCORES = ("ldr_psnr", "hdr_psnr", "ldr_psnr_appearance_fitted")


def add_share_recovered(results: dict) -> dict[str, float]:
    """The PSNR the perturbation cost (clean - perturbed), and in each refined run the share of it
    recovered ((refined - perturbed) / lost), for every score."""
    lost = {key: results["clean"][key] - results["perturbed"][key] for key in SCORES}
    for row in results.values():
        if "pose_errors_refined" in row:
            row["share_recovered"] = {
                key: (row[key] - results["perturbed"][key]) / lost[key] if lost[key] > 0 else math.nan for key in lost
            }
    return lost


def compare_runs(args: argparse.Namespace, clean: SceneData, perturbed: SceneData, radius: float) -> dict:
    """Train clean, perturbed and refined (one run per --camera-opt-lr); each run's held-out figures and
    the refined poses' errors."""
    truth = [view.camera.c2w for view in clean.train]
    given = [view.camera.c2w for view in perturbed.train]
    runs = {
        "clean": (clean, CameraOptConfig(camera_opt="off")),
        "perturbed": (perturbed, CameraOptConfig(camera_opt="off")),
    }
    for lr in args.camera_opt_lr:
        runs[f"refined lr {lr:g}"] = (
            perturbed,
            CameraOptConfig(camera_opt="on", camera_opt_lr=lr, camera_opt_mode=args.camera_opt_mode),
        )
    results: dict = {}
    with tempfile.TemporaryDirectory() as folder:
        for name, (scene, camera) in runs.items():
            trainer, metrics = train_run(args.backbone, scene, args.steps, args.seed, camera, Path(folder) / name)
            keys = (*SCORES, "ldr_ssim", "ldr_ssim_appearance_fitted", "train_seconds", "wall_seconds")
            row = {key: metrics[key] for key in keys}
            if trainer.pipeline.poses is not None:
                with torch.no_grad():
                    refined = [c2w.float() @ trainer.pipeline.poses.correction(i) for i, c2w in enumerate(given)]
                row["pose_errors_refined"] = pose_errors(refined, truth, radius)
                row["pose_errors_refined_whole_pose_fit"] = pose_errors(refined, truth, radius, "poses")
            results[name] = row
            print(name, {k: v for k, v in row.items() if not isinstance(v, dict)}, file=sys.stderr, flush=True)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backbone", default="gs")
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--perturb-poses", type=parse_perturbation, default=(1.0, 0.01), metavar="DEG,FRACTION")
    parser.add_argument("--camera-opt-lr", type=float, nargs="+", default=[CameraOptConfig.camera_opt_lr])
    parser.add_argument("--camera-opt-mode", default=CameraOptConfig.camera_opt_mode)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/pose_refinement"))
    args = parser.parse_args()
    degrees, fraction = args.perturb_poses
    clean = load_scene(DataConfig(scene=args.scene))
    radius = clean.scene_info().extent
    perturbed = perturb_poses(clean, degrees, fraction, args.seed)
    truth = [view.camera.c2w for view in clean.train]
    given = [view.camera.c2w for view in perturbed.train]
    results = compare_runs(args, clean, perturbed, radius)
    lost = add_share_recovered(results)
    command = (
        f"python benchmarks/pose_refinement.py --backbone {args.backbone} --scene {args.scene} --steps {args.steps} "
        f"--seed {args.seed} --perturb-poses {degrees:g},{fraction:g} "
        f"--camera-opt-lr {' '.join(f'{lr:g}' for lr in args.camera_opt_lr)} "
        f"--camera-opt-mode {args.camera_opt_mode}"
    )
    report = {
        "command": command,
        "backbone": args.backbone,
        "scene": args.scene,
        "steps": args.steps,
        "perturbation": {"degrees": degrees, "fraction_of_radius": fraction, "scene_radius": radius},
        "train_views": len(clean.train),
        "test_views": len(clean.test),
        "runs": results,
        "psnr_lost": lost,
        "pose_errors_given": pose_errors(given, truth, radius),
        "pose_errors_given_whole_pose_fit": pose_errors(given, truth, radius, "poses"),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / f"{args.backbone}.json", report)
    (args.out / f"{args.backbone}.md").write_text(markdown(report))


def recovered(figures: dict, *keys: str) -> str:
    """'a % / b %' of the lost PSNR (of each score in `keys`) a refined run recovered, '-' for the others."""
    share = figures.get("share_recovered")
    return " / ".join(f"{100 * share[key]:.0f} %" for key in keys) if share else "-"


def markdown(report: dict) -> str:
    """The report as a Markdown table with its command."""
    runs = report["runs"]
    lines = [
        f"# Pose refinement: {report['backbone']} on {report['scene']}, {report['steps']} steps",
        "",
        f"`{report['command']}`",
        "",
        f"Training poses perturbed by {report['perturbation']['degrees']:g} degree(s) and "
        f"{100 * report['perturbation']['fraction_of_radius']:g} % of the scene radius "
        f"({report['perturbation']['scene_radius']:.3f}), {report['train_views']} training views; "
        f"held-out views ({report['test_views']}) at their exact poses.",
        "",
        "Held-out PSNR in dB: at the exact poses (nerfstudio's protocol: test views are not refined), and on the "
        "right half of each photo with its pose, exposure and white balance fitted on the left half (BARF's "
        "protocol, the same for every run).",
        "",
        "| run | LDR PSNR | HDR PSNR | LDR SSIM | recovered (LDR / HDR) | LDR PSNR, pose fitted | recovered "
        "| train s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, row in runs.items():
        lines.append(
            f"| {name} | {row['ldr_psnr']:.2f} | {row['hdr_psnr']:.2f} | {row['ldr_ssim']:.4f} | "
            f"{recovered(row, 'ldr_psnr', 'hdr_psnr')} | {row['ldr_psnr_appearance_fitted']:.2f} | "
            f"{recovered(row, 'ldr_psnr_appearance_fitted')} | {row['train_seconds']:.0f} |"
        )
    lost = report["psnr_lost"]
    lines += [
        "",
        f"Lost to the perturbation: LDR {lost['ldr_psnr']:.2f} dB, HDR {lost['hdr_psnr']:.2f} dB at the exact poses; "
        f"LDR {lost['ldr_psnr_appearance_fitted']:.2f} dB with the poses fitted.",
        "",
        "Pose errors against the truth, with the gauge removed by a similarity fit of the camera centres, or of "
        "whole poses (the rotation from the cameras' orientations):",
        "",
        "| poses | gauge fit | rotation mean (deg) | median | max | centre mean (radius) | max |",
        "|---|---|---|---|---|---|---|",
    ]
    rows = [("given (perturbed)", report["pose_errors_given"], report["pose_errors_given_whole_pose_fit"])]
    rows += [
        (name, row["pose_errors_refined"], row["pose_errors_refined_whole_pose_fit"])
        for name, row in runs.items()
        if "pose_errors_refined" in row
    ]
    for name, centres, whole in rows:
        for gauge, errors in (("centres", centres), ("whole poses", whole)):
            lines.append(
                f"| {name} | {gauge} | {errors['rotation_degrees_mean']:.3f} | "
                f"{errors['rotation_degrees_median']:.3f} | {errors['rotation_degrees_max']:.3f} | "
                f"{errors['translation_radius_mean']:.4f} | "
                f"{errors['translation_radius_max']:.4f} |"
            )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
