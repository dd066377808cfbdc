"""Pose refinement in a training run (core.camera_optimizer): whether the run refines, what it writes
to OUT/refined_poses.json, and the check that a resumed run refines as its checkpoint did."""

from pathlib import Path
from typing import Any

from rich.console import Console

from mono_hdr_plugin.core.camera_optimizer import CameraOptConfig, PoseCorrections, build_pose_corrections
from mono_hdr_plugin.core.registry import get_backbone
from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.training.pipeline import Pipeline
from mono_hdr_plugin.training.resume import ResumeMismatch

REFINED_POSES_FILE = "refined_poses.json"
console = Console(stderr=True)


def run_pose_corrections(config: CameraOptConfig, scene: SceneData, backbone_name: str) -> PoseCorrections | None:
    """The pose corrections of a run of `backbone_name` on `scene` (None: poses as given); the
    translation learned in units of the scene's radius (SceneInfo.extent)."""
    differentiable = get_backbone(backbone_name).differentiable_pose
    return build_pose_corrections(config, scene, scene.scene_info().extent, differentiable, backbone_name)


def write_refined_poses(pipeline: Pipeline, scene: SceneData, out: Path, step: int, quiet: bool) -> Path | None:
    """Write OUT/refined_poses.json atomically (a temporary file renamed), every training view's pose
    as given and as refined, and say so unless `quiet`; nothing without refinement."""
    if pipeline.poses is None:
        return None
    path = out / REFINED_POSES_FILE
    cameras, names = [view.camera for view in scene.train], [view.name for view in scene.train]
    write_json(path, {"step": step, **pipeline.poses.report(cameras, names)})
    if not quiet:
        console.print(f"refined training poses written to {path}", markup=False, soft_wrap=True)
    return path


def check_resumed_refinement(payload: dict[str, Any], pipeline: Pipeline, checkpoint: Path) -> None:
    """Refuse to resume a checkpoint with pose refinement turned the other way: its state dict has
    corrections these flags would drop, or lacks the ones they would learn."""
    refined = any(key.startswith("poses.") for key in payload["pipeline"])
    if refined != (pipeline.poses is not None):
        was, now = ("on", "off") if refined else ("off", "on")
        raise ResumeMismatch(
            f"cannot resume from {checkpoint}: it was trained with pose refinement {was}, these flags turn "
            f"it {now}: pass --camera-opt {was} to continue it, or train into another --out"
        )
