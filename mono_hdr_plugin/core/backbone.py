"""The one interface between the meta-algorithm and a 3D backbone.

A backbone knows geometry and how to composite; it knows nothing about HDR. It hands out
per-primitive LDR colours plus a compositing function that renders ANY number of channels
with the same weights, so the wrapper can render LDR and HDR in one pass.
"""

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor

from mono_hdr_plugin.core.cameras import Camera

# Learning rate of the HDR converters in both official codes (hard-coded there).
OFFICIAL_CONVERTER_LR = 5e-4


@dataclass
class LdrFeatures:
    """What a backbone renders for one camera (or one pixel batch of it).

    colors: [..., P, 3] per-primitive LDR colours in [0, 1] (P Gaussians, or P samples per ray).
    raw_colors: [..., P, 3] the same colours before the backbone's LDR activation (unbounded);
        baseline methods read them as log radiance, as HDR-NeRF and HDR-GS do.
    composite: values [..., P, C] -> image [*camera.output_shape, C], with the backbone's
        weights (alpha blending, volume-rendering weights); any C, one pass.
    extras: backbone outputs the wrapper passes through: "depth" and "alpha" [*output_shape]
        where they come with the colours (NeRF), "render_depth" (a function returning depth)
        where depth costs an extra pass (3DGS), 2D means, ...
    auxiliary: further renders supervised with the LDR loss only (NeRF's coarse network).
    l2h_inputs: [..., P, 3] what L2H-CC reads instead of `colors`, where the backbone has a
        coordinate of the same colours in which the HDR loss's gradient does not vanish (the NeRF
        grid field's logits); None: `colors`.
    """

    colors: Tensor
    raw_colors: Tensor
    composite: Callable[[Tensor], Tensor]
    extras: dict[str, Any] = field(default_factory=dict)
    auxiliary: list["LdrFeatures"] = field(default_factory=list)
    l2h_inputs: Tensor | None = None


@dataclass
class SceneInfo:
    """What a backbone may know about a scene before training: bounds, init points, cameras."""

    bounds_min: Tensor
    bounds_max: Tensor
    train_cameras: list[Camera]
    points: Tensor | None = None
    point_colors: Tensor | None = None
    unbounded: bool = False
    """Whether the scene reaches to infinity (open sky, a distant horizon): backbones then add what lies
    at infinity (3DGS an environment map, NeRF a contracted space and a background) unless their
    flags say otherwise. The data sets it (docs/outdoor.md says how it is decided)."""

    @property
    def center(self) -> Tensor:
        return 0.5 * (self.bounds_min + self.bounds_max)

    @property
    def extent(self) -> float:
        """Radius of the camera rig, as 3DGS uses for its densification thresholds.

        No camera, a single camera or cameras at one spot have no rig: half the scene diagonal
        stands in.
        """
        if self.train_cameras:
            centers = torch.stack([c.center.float() for c in self.train_cameras])
            rig = float(1.1 * (centers - centers.mean(0)).norm(dim=-1).max())
            if rig > 1e-6:
                return rig
        return max(0.5 * float((self.bounds_max - self.bounds_min).float().norm()), 1e-3)


class Backbone(torch.nn.Module):
    """Base class of every backbone: subclass, set `config_class`, implement `render_ldr_features`.

    Class attributes a backbone sets:
        config_class: its dataclass of hyper-parameters (tyro turns the fields into flags).
        loss_kind: "l1_dssim" (3DGS photometric loss) or "mse" (NeRF), the method's default.
        pixel_batch: None to train on whole images, or the number of rays per step.
        render_chunk: None to render whole images in one call, or the most rays per call.
        converter_lr: learning rate of the method's networks unless --converter-lr is given: the
            official codes' 5e-4; a backbone whose own networks learn much faster raises it, so
            the converters keep pace with the colours they convert (the official NeRF trains both
            at one rate).
        paper_backbone: which of the paper's backbones this one reproduces, "NeRF" or "3DGS";
            `mono-hdr bench` compares it with the paper's figures of that row (None: no row).
        differentiable_pose: whether `render_ldr_features` passes gradients to `camera.c2w`, which
            camera pose refinement (`--camera-opt`, core.camera_optimizer) needs: a backbone that
            builds its rays with `camera.rays()` or projects with `camera.w2c` in torch gets it for
            free; one whose renderer takes the pose as a constant sets False, and refinement then
            stays off (3DGS's C++ projection moves the world instead of the camera: backbones.gs.model).

    A backbone whose parameter shapes change while training (3DGS densification) overrides
    torch's `_load_from_state_dict` to take a checkpoint's shapes, so resuming just works.
    Everything else that shapes a render must reach `state_dict()` too, as a buffer or through
    torch's `get_extra_state`/`set_extra_state` (3DGS: the active SH degree): checkpoints hold
    the state dict and nothing else of the backbone.
    """

    config_class: ClassVar[type]
    loss_kind: ClassVar[Literal["l1_dssim", "mse"]] = "l1_dssim"
    paper_backbone: ClassVar[str | None] = None
    differentiable_pose: ClassVar[bool] = True
    pixel_batch: int | None = None  # a backbone may set these per instance (NeRF: from its config)
    render_chunk: int | None = None
    converter_lr: float = OFFICIAL_CONVERTER_LR

    def __init__(self, config: Any, scene: SceneInfo):
        super().__init__()
        self.config = config
        self.max_steps = 30_000

    @classmethod
    def tuning_space(cls, config: Any) -> dict[str, tuple]:
        """What `mono-hdr bench paper`'s recipe table tunes for every method alike, for runs with
        `config` (a preset's): a field path of the config -> candidate values (each method gets
        the same grid)."""
        return {}

    @classmethod
    def presets(cls) -> dict[str, Any]:
        """Named configurations of this backbone (`--preset NAME`); the first one is the default."""
        return {"default": cls.config_class()}

    def statistics(self) -> dict[str, float]:
        """Numbers the benchmarks report next to quality (3DGS: the Gaussian count)."""
        return {}

    def set_run_length(self, max_steps: int) -> None:
        """Told by the trainer before step 0, so schedules (densification) scale to the run.

        Under a time budget (`--max-seconds`) the trainer calls it again while training with its
        latest estimate of the steps that fit: rescale schedules, keep all learned state.
        """
        self.max_steps = max_steps

    @property
    def coarse_to_fine_pays(self) -> bool:
        """Whether `--pyramid-levels` left automatic trains this backbone coarse-to-fine on large views
        (pyramid.automatic_levels): one that renders whole images (a coarse step renders fewer pixels) does;
        one on ray batches (the same cost) not."""
        return self.pixel_batch is None

    def set_image_scale(self, scale: float) -> None:
        """Told by the trainer when coarse-to-fine training (`--pyramid-levels`) moves to another level:
        training images are now `scale` (1/2^k) of the full size a side. A backbone whose capacity
        follows the training pixels (a 3DGS Gaussian budget) sizes it to them."""

    def parameter_groups(self) -> list[dict]:
        """Optimiser groups: dicts with "name", "params" and "lr" (Adam is used)."""
        return [{"name": "backbone", "params": list(self.parameters()), "lr": 1e-3}]

    def render_ldr_features(self, camera: Camera) -> LdrFeatures:
        raise NotImplementedError

    def after_step(self, step: int, features: LdrFeatures, optimizer: torch.optim.Optimizer) -> None:
        """Called after each optimiser step, before gradients are cleared: densification, ...

        Gradients of the tensors the backbone put in `features.extras` (3DGS: the screen-space
        means) are still readable here. A backbone that adds or removes parameters must keep
        `optimizer` state in step (its param_groups carry the "name" keys given above).
        """

    def visible_rows(self, features: LdrFeatures) -> Tensor | None:
        """Which rows of the "per_row" parameter groups the render behind `features` touched: region
        training steps only those (training.visible_adam). None: every row (no such groups)."""
        return None

    def learning_rate(self, group_name: str, step: int, base_lr: float) -> float:
        """Per-group learning rate at `step`; override for schedules (3DGS position decay)."""
        return base_lr

    def regularisation(self) -> dict[str, Tensor]:
        """Named loss terms on the backbone's own parameters, added to the method's losses each
        training step (3DGS-MCMC: opacity and scale regularisers)."""
        return {}
