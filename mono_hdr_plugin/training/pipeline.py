"""A backbone and the method that lifts it to HDR: the one object that trains, renders and is saved.

    pipeline = Pipeline.create("gs", GaussianConfig(), MethodConfig(method="mono"), scene.scene_info())
    output = pipeline.render(camera, exposure)          # whole image, chunked when the backbone asks

Training (`mono_hdr_plugin.training.trainer.Trainer`), evaluation, `mono-hdr render`, the viewer and the
benchmarks all go through it; a checkpoint holds its `state_dict()` (backbone.*, method.*).
"""

import contextlib
import dataclasses
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from mono_hdr_plugin.core.backbone import Backbone, LdrFeatures, SceneInfo
from mono_hdr_plugin.core.calibration import RadianceCalibration
from mono_hdr_plugin.core.camera_optimizer import PoseCorrections
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.core.exposure import ViewExposures
from mono_hdr_plugin.core.registry import get_backbone
from mono_hdr_plugin.methods.base import (
    UNBOUNDED_HDR_LOG_WEIGHT,
    HdrMethod,
    MethodConfig,
    MethodOutput,
    Targets,
    build_method,
)

OWNERS = ("backbone", "method", "exposures", "poses")


class RenderCancelled(Exception):
    """A render was abandoned between two pixel chunks because its result is no longer wanted."""


@dataclass
class Frame:
    """One rendered view, linear.

    ldr: [H, W, 3] the LDR render at `exposure` (clamped to [0, 1]).
    hdr: [H, W, 3] linear HDR radiance, calibrated (`Pipeline.calibration`).
    A camera with `pixels` set gives [N, 3] / [N] images of those pixels.
    depth: [H, W] the backbone's depth, None when it gives none.
    alpha: [H, W] accumulated opacity (1: the ray hit something), None when the backbone gives none.
    """

    ldr: torch.Tensor
    hdr: torch.Tensor
    depth: torch.Tensor | None
    alpha: torch.Tensor | None
    exposure: float


class Pipeline(nn.Module):
    """`backbone` renders per-primitive LDR features; `method` lifts them to HDR and scores them;
    `exposures` (optional, mono_hdr_plugin.core.exposure) gives each training view its own exposure;
    `poses` (optional, mono_hdr_plugin.core.camera_optimizer) refines each training view's pose;
    `calibration` sets the absolute level of every rendered HDR image (core.calibration; fitted by
    training.calibration, saved with the model as its extra state)."""

    def __init__(
        self,
        backbone_name: str,
        backbone: Backbone,
        method: HdrMethod,
        exposures: ViewExposures | None = None,
        poses: PoseCorrections | None = None,
    ):
        super().__init__()
        self.backbone_name = backbone_name
        self.backbone = backbone
        self.method = method
        self.exposures = exposures
        self.poses = poses
        self.calibration = RadianceCalibration()

    @classmethod
    def create(
        cls,
        backbone_name: str,
        backbone_config: Any,
        method_config: MethodConfig,
        scene: SceneInfo,
        exposures: ViewExposures | None = None,
        poses: PoseCorrections | None = None,
    ) -> "Pipeline":
        """A fresh pipeline: the registered backbone `backbone_name` and the method the config names."""
        backbone_class = get_backbone(backbone_name)
        backbone = backbone_class(backbone_config, scene)
        if method_config.converter_lr is None:  # the backbone's default rate for the method's networks
            method_config = dataclasses.replace(method_config, converter_lr=backbone.converter_lr)
        if method_config.hdr_log_weight is None:
            weight = UNBOUNDED_HDR_LOG_WEIGHT if scene.unbounded else 0.0
            method_config = dataclasses.replace(method_config, hdr_log_weight=weight)
        method = build_method(method_config, backbone_class.loss_kind)
        return cls(backbone_name, backbone, method, exposures, poses)

    @property
    def method_name(self) -> str:
        return self.method.config.method

    def get_extra_state(self) -> dict:
        return {"radiance_calibration": self.calibration.state()}

    def set_extra_state(self, state: dict) -> None:
        self.calibration = RadianceCalibration.from_state(state["radiance_calibration"])

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Also a state saved before calibration existed: it loads uncalibrated (the loader fits one)."""
        if "_extra_state" not in state_dict:
            state_dict = {**state_dict, "_extra_state": {"radiance_calibration": RadianceCalibration().state()}}
        return super().load_state_dict(state_dict, strict, assign)

    # ------------------------------------------------------------------ training
    def parameter_groups(self) -> list[dict]:
        """Adam groups of backbone and method, each tagged with its "owner" (whose schedule applies).

        Group names must be unique across the two: resume and density control find groups by name.
        """
        groups, seen = [], set()
        for owner in OWNERS:
            if getattr(self, owner) is None:
                continue
            for group in getattr(self, owner).parameter_groups():
                if group["name"] in seen:
                    raise ValueError(
                        f"optimiser group name {group['name']!r} is used by both the backbone "
                        f"{self.backbone_name!r} and the method {self.method_name!r}; rename one"
                    )
                seen.add(group["name"])
                groups.append({**group, "owner": owner})
        return groups

    def learning_rate(self, group: dict, step: int) -> float:
        """The learning rate of an optimiser group (from `parameter_groups`) at `step`."""
        owner: Backbone | HdrMethod | ViewExposures | PoseCorrections = getattr(self, group["owner"])
        return owner.learning_rate(group["name"], step, group["base_lr"])

    def set_run_length(self, steps: int) -> None:
        self.backbone.set_run_length(steps)
        if self.poses is not None:
            self.poses.run_length = steps

    def set_image_scale(self, scale: float) -> None:
        self.backbone.set_image_scale(scale)

    @property
    def renders_any_exposure(self) -> bool:
        """Whether LDR renders follow the requested exposure: methods that take exposure, and any
        method once views have their own exposures (Mono-HDR through the brightness term)."""
        return self.method.renders_any_exposure or self.exposures is not None

    def _lift(self, features: LdrFeatures, exposure: float, view: int | None, training: bool) -> MethodOutput:
        """The method's images at `exposure`, or at training view `view`'s own exposure."""
        lift = self.method.render if training else self.method
        if self.exposures is None:
            return lift(features, exposure)
        log_scale = self.exposures.log_scale(view, exposure)  # per channel where white balance is learned
        if self.method.renders_any_exposure:
            return lift(features, self.exposures.reference_exposure * torch.exp(log_scale))
        output = lift(features, exposure)
        output.ldr = self.exposures.brighten(output.ldr, log_scale)
        output.auxiliary_ldr = [self.exposures.brighten(aux, log_scale) for aux in output.auxiliary_ldr]
        if output.ldr_from_hdr is not None:
            output.ldr_from_hdr = self.exposures.brighten(output.ldr_from_hdr, log_scale)
        return output

    def forward(self, camera: Camera, exposure: float, view: int | None = None) -> tuple[LdrFeatures, MethodOutput]:
        """One training render: the backbone's features (for after_step) and the method's images, at
        training view `view`'s own (possibly learned) exposure when views have their own, from its
        refined pose when poses are refined."""
        if self.poses is not None and view is not None:
            camera = self.poses.refine(camera, view)
        features = self.backbone.render_ldr_features(camera)
        return features, self._lift(features, exposure, view, training=True)

    def losses(self, output: MethodOutput, targets: Targets, step: int) -> dict[str, torch.Tensor]:
        """The method's loss terms and the regularisers of backbone and white balance; the training loss
        is their sum."""
        terms = {**self.method.losses(output, targets, step), **self.backbone.regularisation()}
        return terms if self.exposures is None else {**terms, **self.exposures.regularisation()}

    def after_step(self, step: int, features: LdrFeatures, optimizer: torch.optim.Optimizer) -> None:
        self.check_pose_gradient()
        self.backbone.after_step(step, features, optimizer)

    def check_pose_gradient(self) -> None:
        """Refuse a step that left every pose correction without a gradient: a backbone that renders the
        pose as a constant but declares `differentiable_pose` would keep them at zero without a word."""
        if self.poses is not None and all(p.grad is None for p in self.poses.corrections):
            raise RuntimeError(
                f"--camera-opt: the backbone {self.backbone_name!r} gave no gradient to the camera pose, so "
                "poses cannot be refined; pass --camera-opt off, or set differentiable_pose = False on the "
                "backbone class (core/backbone.py says what it means)"
            )

    # ----------------------------------------------------------------- rendering
    def camera_chunks(self, camera: Camera) -> list[Camera]:
        """The camera split into pixel batches of `backbone.render_chunk` rays (whole if None)."""
        if self.backbone.render_chunk is None:
            return [camera]
        return [camera.with_pixels(pixels) for pixels in camera.pixel_centers().split(self.backbone.render_chunk)]

    @torch.no_grad()
    def render(
        self, camera: Camera, exposure: float, cancelled: Callable[[], bool] | None = None, with_depth: bool = False
    ) -> Frame:
        """A whole image at `exposure` seconds (or the camera's `pixels`), in pieces of
        `backbone.render_chunk` rays; the HDR calibrated.

        `cancelled` is asked between pieces; a True answer raises RenderCancelled (the viewer's
        camera moved on). Depth and opacity come with the colours where the backbone composites
        them (NeRF); where depth costs an extra pass (3DGS's "render_depth"), only `with_depth`.
        """
        ldr: list[torch.Tensor] = []
        hdr: list[torch.Tensor] = []
        depth: list[torch.Tensor | None] = []
        alpha: list[torch.Tensor | None] = []
        for part in self.camera_chunks(camera):
            if cancelled is not None and cancelled():
                raise RenderCancelled
            features = self.backbone.render_ldr_features(part)
            output = self._lift(features, exposure, None, training=False)
            ldr.append(output.ldr.reshape(-1, 3))
            hdr.append(output.hdr.reshape(-1, 3))
            part_depth = features.extras.get("depth")
            if with_depth and "render_depth" in features.extras:
                part_depth = features.extras["render_depth"]()
            for value, pieces in ((part_depth, depth), (features.extras.get("alpha"), alpha)):
                pieces.append(None if value is None else value.reshape(-1))
        shape = (camera.height, camera.width) if camera.pixels is None else (len(camera.pixels),)

        def image(pieces: list[torch.Tensor | None]) -> torch.Tensor | None:
            present = [piece for piece in pieces if piece is not None]
            return None if len(present) < len(pieces) else torch.cat(present).reshape(shape)

        return Frame(
            ldr=torch.cat(ldr).reshape(*shape, 3).clamp(0.0, 1.0),
            hdr=torch.cat(hdr).reshape(*shape, 3) * self.calibration.scale,
            depth=image(depth),
            alpha=image(alpha),
            exposure=exposure,
        )

    @contextlib.contextmanager
    def evaluating(self) -> Iterator["Pipeline"]:
        """Eval mode (deterministic sampling) inside the block, the previous mode after it."""
        was_training = self.training
        self.eval()
        try:
            yield self
        finally:
            self.train(was_training)
