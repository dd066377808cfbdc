"""Loading a trained model from a checkpoint: the one loader of eval, render, view, export and
the benchmarks."""

import dataclasses
import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

from mono_hdr_plugin.core.camera_optimizer import PoseCorrections
from mono_hdr_plugin.core.exposure import ViewExposures
from mono_hdr_plugin.core.registry import get_backbone
from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.training.calibration import fit_radiance_calibration
from mono_hdr_plugin.training.checkpoints import CheckpointError, load_checkpoint
from mono_hdr_plugin.training.config import TrainConfig, hdr_supervised_views, saved_train_config
from mono_hdr_plugin.training.frames import ExposureModel, calibrate
from mono_hdr_plugin.training.pipeline import Pipeline
from mono_hdr_plugin.training.resume import check_scored_data


@dataclass
class TrainedModel:
    """A trained model ready to evaluate or render (no optimiser): its pipeline in eval mode, the
    scene it renders (cameras, ground truth), its run settings, and the step and training time
    its checkpoint reached."""

    pipeline: Pipeline
    scene: SceneData
    config: TrainConfig
    step: int
    train_seconds: float

    @property
    def backbone(self):
        return self.pipeline.backbone

    @property
    def method(self):
        return self.pipeline.method

    @cached_property
    def exposure(self) -> ExposureModel:
        """The display scale and reference exposure of render, view and export; fitted on first use
        (it renders a few training views), so evaluation does not pay for it."""
        return calibrate(self.pipeline, self.scene)


def load_trained_model(
    checkpoint: Path, scene: SceneData | None = None, data_path: Path | None = None, scene_name: str | None = None
) -> TrainedModel:
    """The trained model of a checkpoint file written by `mono-hdr train`, with its own data unless
    other data is given (an in-memory `scene`, a dataset folder or a built-in scene name)."""
    payload = load_checkpoint(checkpoint)
    backbone_class = get_backbone(payload["backbone_name"])
    try:
        config = saved_train_config(backbone_class.config_class, json.loads(payload["config"]))
    except (KeyError, TypeError, ValueError) as error:
        raise CheckpointError(
            f"{checkpoint}: its run settings cannot be read by this version ({error}); "
            "retrain, or install the version that wrote it"
        ) from error
    if data_path is not None or scene_name is not None:
        config.data = dataclasses.replace(config.data, data=data_path, scene=scene_name)
    if scene is None:
        from mono_hdr_plugin.core.metrics import SSIM_WINDOW
        from mono_hdr_plugin.data.loading import load_scene

        scene = load_scene(config.data, min_side=SSIM_WINDOW)
    if data_path is not None or scene_name is not None:
        check_scored_data(payload.get("data"), scene, checkpoint, "--data" if data_path is not None else "--scene")
    pipeline = Pipeline.create(
        payload["backbone_name"],
        config.backbone,
        config.hdr,
        scene.scene_info(),
        ViewExposures.from_state_dict(payload["pipeline"]),
        PoseCorrections.from_state_dict(payload["pipeline"]),
    )
    pipeline.set_run_length(payload["run_length"])
    try:
        pipeline.load_state_dict(payload["pipeline"])
    except (RuntimeError, KeyError) as error:
        raise CheckpointError(
            f"{checkpoint}: its model does not fit the {payload['backbone_name']!r} model of this "
            f"version ({str(error).strip().splitlines()[0][:200]}); retrain, or install the version "
            "that wrote it"
        ) from error
    pipeline.eval()
    if not pipeline.calibration.fitted:  # a checkpoint written before calibration existed
        hdr_views = hdr_supervised_views(len(scene.train), config.hdr_view_ratio)
        pipeline.calibration = fit_radiance_calibration(pipeline, scene, payload["step"], hdr_views)
    return TrainedModel(pipeline, scene, config, payload["step"], payload["train_seconds"])
