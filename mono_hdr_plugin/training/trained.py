"""Loading a trained pipeline from a checkpoint: the one loader of eval, render, view, export and
the benchmarks."""

import dataclasses
import json
from pathlib import Path
from typing import Any, NamedTuple

from mono_hdr_plugin.core.exposure import ViewExposures
from mono_hdr_plugin.core.registry import get_backbone
from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.training.checkpoints import CheckpointError, load_checkpoint
from mono_hdr_plugin.training.config import TrainConfig, saved_train_config
from mono_hdr_plugin.training.pipeline import Pipeline

class TrainedRun(NamedTuple):
    """A pipeline loaded from a checkpoint for evaluation or rendering (no optimiser)."""

    pipeline: Pipeline
    scene: SceneData
    config: TrainConfig
    payload: dict[str, Any]


def load_pipeline(checkpoint: Path, scene: SceneData | None = None, data_path: Path | None = None,
                  scene_name: str | None = None) -> TrainedRun:
    """The trained pipeline of a checkpoint file, with its own data unless other data is given
    (an in-memory `scene`, a dataset folder or a built-in scene name)."""
    payload = load_checkpoint(checkpoint)
    backbone_class = get_backbone(payload["backbone_name"])
    try:
        config = saved_train_config(backbone_class.config_class, json.loads(payload["config"]))
    except (KeyError, TypeError, ValueError) as error:
        raise CheckpointError(f"{checkpoint}: its run settings cannot be read by this version ({error}); "
                              "retrain, or install the version that wrote it") from error
    if data_path is not None or scene_name is not None:
        config.data = dataclasses.replace(config.data, data=data_path, scene=scene_name)
    if scene is None:
        from mono_hdr_plugin.data.loading import load_scene  # noqa: PLC0415

        scene = load_scene(config.data)
    pipeline = Pipeline.create(payload["backbone_name"], config.backbone, config.hdr, scene.scene_info(),
                               ViewExposures.from_state_dict(payload["pipeline"]))
    pipeline.set_run_length(payload["run_length"])
    try:
        pipeline.load_state_dict(payload["pipeline"])
    except (RuntimeError, KeyError) as error:
        raise CheckpointError(f"{checkpoint}: its model does not fit the {payload['backbone_name']!r} model of this "
                              f"version ({str(error).strip().splitlines()[0][:200]}); retrain, or install the version "
                              "that wrote it") from error
    pipeline.eval()
    return TrainedRun(pipeline, scene, config, payload)
