"""A backbone and the method that lifts it to HDR: the one object that trains, renders and is saved.

    pipeline = Pipeline.create("gs", GaussianConfig(), MethodConfig(method="mono"), scene.scene_info())
    output = pipeline.render(camera, exposure)          # whole image, chunked when the backbone asks

Training (`mono_hdr_plugin.train.Trainer`), evaluation, `mono-hdr render`, the viewer and the
benchmarks all go through it; a checkpoint holds its `state_dict()` (backbone.*, method.*).
"""

import contextlib
from collections.abc import Iterator
from typing import Any

import torch
from torch import nn

from mono_hdr_plugin.backbone import Backbone, LdrFeatures, SceneInfo
from mono_hdr_plugin.cameras import Camera
from mono_hdr_plugin.methods import HdrMethod, MethodConfig, MethodOutput, Targets, build_method
from mono_hdr_plugin.registry import get_backbone

OWNERS = ("backbone", "method")


class Pipeline(nn.Module):
    """`backbone` renders per-primitive LDR features; `method` lifts them to HDR and scores them."""

    def __init__(self, backbone_name: str, backbone: Backbone, method: HdrMethod):
        super().__init__()
        self.backbone_name = backbone_name
        self.backbone = backbone
        self.method = method

    @classmethod
    def create(cls, backbone_name: str, backbone_config: Any, method_config: MethodConfig,
               scene: SceneInfo) -> "Pipeline":
        """A fresh pipeline: the registered backbone `backbone_name` and the method the config names."""
        backbone_class = get_backbone(backbone_name)
        backbone = backbone_class(backbone_config, scene)
        return cls(backbone_name, backbone, build_method(method_config, backbone_class.loss_kind))

    @property
    def method_name(self) -> str:
        return self.method.config.method

    # ------------------------------------------------------------------ training
    def parameter_groups(self) -> list[dict]:
        """Adam groups of backbone and method, each tagged with its "owner" (whose schedule applies).

        Group names must be unique across the two: resume and density control find groups by name.
        """
        groups, seen = [], set()
        for owner in OWNERS:
            for group in getattr(self, owner).parameter_groups():
                if group["name"] in seen:
                    raise ValueError(f"optimiser group name {group['name']!r} is used by both the backbone "
                                     f"{self.backbone_name!r} and the method {self.method_name!r}; rename one")
                seen.add(group["name"])
                groups.append({**group, "owner": owner})
        return groups

    def learning_rate(self, group: dict, step: int) -> float:
        """The learning rate of an optimiser group (from `parameter_groups`) at `step`."""
        owner: Backbone | HdrMethod = getattr(self, group["owner"])
        return owner.learning_rate(group["name"], step, group["base_lr"])

    def set_run_length(self, steps: int) -> None:
        self.backbone.set_run_length(steps)

    def forward(self, camera: Camera, exposure: float) -> tuple[LdrFeatures, MethodOutput]:
        """One training render: the backbone's features (for after_step) and the method's images."""
        features = self.backbone.render_ldr_features(camera)
        return features, self.method.render(features, exposure)

    def losses(self, output: MethodOutput, targets: Targets, step: int) -> dict[str, torch.Tensor]:
        """The method's loss terms and the backbone's regularisers; the training loss is their sum."""
        return {**self.method.losses(output, targets, step), **self.backbone.regularisation()}

    def after_step(self, step: int, features: LdrFeatures, optimizer: torch.optim.Optimizer) -> None:
        self.backbone.after_step(step, features, optimizer)

    # ----------------------------------------------------------------- rendering
    def camera_chunks(self, camera: Camera) -> list[Camera]:
        """The camera split into pixel batches of `backbone.render_chunk` rays (whole if None)."""
        if self.backbone.render_chunk is None:
            return [camera]
        return [camera.with_pixels(pixels) for pixels in camera.pixel_centers().split(self.backbone.render_chunk)]

    @torch.no_grad()
    def render(self, camera: Camera, exposure: float) -> MethodOutput:
        """A whole image at `exposure` seconds: ldr and hdr [H, W, 3]."""
        parts = [self.method(self.backbone.render_ldr_features(part), exposure) for part in self.camera_chunks(camera)]
        shape = (camera.height, camera.width, 3)
        return MethodOutput(ldr=torch.cat([p.ldr for p in parts]).reshape(shape),
                            hdr=torch.cat([p.hdr for p in parts]).reshape(shape))

    @contextlib.contextmanager
    def evaluating(self) -> Iterator["Pipeline"]:
        """Eval mode (deterministic sampling) inside the block, the previous mode after it."""
        was_training = self.training
        self.eval()
        try:
            yield self
        finally:
            self.train(was_training)
