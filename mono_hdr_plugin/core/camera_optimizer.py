"""Camera pose refinement: a learned rigid correction of every training view's pose.

Poses from structure from motion are a little wrong (a fraction of a degree, a fraction of a percent
of the scene), and a model trained on them blurs what the views disagree on. As nerfstudio's camera
optimiser does, each training view gets a 6-vector (translation, rotation), zero at the start, whose
exponential map corrects the pose in the camera's own frame:

    c2w_refined = c2w @ exp(correction)

The correction is learned with the model by the same loss. Backbones see only a `Camera` whose
`c2w` requires grad (`PoseCorrections.refine`), so one that builds its rays from the pose in torch
gets the gradient for free; one whose renderer takes the pose as a constant declares it
(`Backbone.differentiable_pose`). Held-out views are not refined: they are scored at their poses as
given (nerfstudio does the same). `--camera-opt auto` (the default) refines where the data's poses
come from structure from motion (`scene.metadata["poses"]`, set by each layout) and not where they
are exact (the studio's scenes); the default is off until refinement stops costing held-out quality
on real captures (docs/real_photos.md).
"""

import math
from dataclasses import dataclass, replace
from typing import ClassVar, Literal

import torch
from torch import Tensor, nn

from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.core.validation import NON_NEGATIVE, POSITIVE, FlagError, one_of

STRUCTURE_FROM_MOTION = "structure-from-motion"
"""scene.metadata["poses"] of data whose poses were estimated (COLMAP, LLFF, process-data)."""
EXACT = "exact"
"""scene.metadata["poses"] of data whose poses are the renderer's own (the studio, Blender scenes)."""
FINAL_LR_SHARE = 0.01
"""The corrections' learning rate decays exponentially to this share of --camera-opt-lr at the run's
end (nerfstudio's camera optimiser: 6e-4 to 6e-6), so the poses settle instead of jittering by about
one learning rate a step."""
SMALL_ANGLE = 1e-4
"""Below this rotation angle (radians) the exponential map uses its Taylor series."""


@dataclass
class CameraOptConfig:
    """Refinement of the training views' poses (nerfstudio's camera optimiser)."""

    camera_opt: Literal["auto", "on", "off"] = "off"
    """Learn a rigid correction of every training view's pose with the model. auto: on where the
    poses come from structure from motion (process-data, COLMAP and LLFF folders), off where they are
    exact (--scene, Blender scenes). Held-out views keep their poses. The refined poses are written
    to OUT/refined_poses.json. Off by default: on a real street (opensfm_lund, 10 minutes) refinement
    cost 3.8 dB on the held-out views, whose poses it does not move (docs/real_photos.md)."""
    camera_opt_mode: Literal["SO3xR3", "SE3"] = "SO3xR3"
    """How the 6-vector becomes a pose: SO3xR3 (rotation and translation apart, nerfstudio's default)
    or SE3 (the exponential map of the rigid motion)."""
    camera_opt_lr: float = 1e-2
    """Adam learning rate of the corrections at the start (radians, and scene radii for the translation);
    it decays exponentially to 1 % of this at the run's end."""
    camera_opt_weight_decay: float = 0.0
    """Adam weight decay of the corrections: a pull toward the poses as given."""
    eval_pose: Literal["auto", "on", "off"] = "auto"
    """Fit each held-out view's pose on the left half of its photo (with the model frozen) before the
    held-out protocol scores the right half (BARF's protocol; docs/own_photos.md). auto: where training
    refined its poses, which moves the model's world a little from the poses as given. The scores as
    given (ldr_psnr) always render the given pose."""

    flag_rules: ClassVar = {
        "camera_opt": one_of("auto", "on", "off"),
        "camera_opt_mode": one_of("SO3xR3", "SE3"),
        "camera_opt_lr": POSITIVE,
        "camera_opt_weight_decay": NON_NEGATIVE,
        "eval_pose": one_of("auto", "on", "off"),
    }


def skew(vector: Tensor) -> Tensor:
    """The cross-product matrix [3, 3] of `vector` [3]: skew(a) @ b == a x b."""
    x, y, z = vector.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero]).reshape(3, 3)


def _series(rotation: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Skew matrix K of `rotation` [3] and the coefficients sin t / t, (1 - cos t) / t^2 and
    (t - sin t) / t^3 of t = |rotation|, by their Taylor series near zero (finite gradients at 0)."""
    theta2 = (rotation * rotation).sum()
    small = theta2 < SMALL_ANGLE**2
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)  # no 0 / 0 in the branch not taken
    theta = torch.sqrt(safe2)
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / safe2)
    c = torch.where(small, 1 / 6 - theta2 / 120, (theta - torch.sin(theta)) / (safe2 * theta))
    return skew(rotation), a, b, c


def so3_exp(rotation: Tensor) -> Tensor:
    """Rotation matrix [3, 3] of the axis-angle vector `rotation` [3] (Rodrigues' formula)."""
    k, a, b, _ = _series(rotation)
    return torch.eye(3, dtype=rotation.dtype) + a * k + b * (k @ k)


def pose_exp(tangent: Tensor, mode: str = "SO3xR3") -> Tensor:
    """The rigid motion [4, 4] of a 6-vector (translation, rotation).

    SO3xR3: rotation exp(rotation), translation as given. SE3: the exponential map of the twist,
    whose translation is V(rotation) @ translation (a screw motion). Zero gives the identity in both.
    """
    translation, rotation = tangent[:3], tangent[3:]
    k, a, b, c = _series(rotation)
    eye = torch.eye(3, dtype=tangent.dtype)
    matrix = eye + a * k + b * (k @ k)
    if mode == "SE3":
        translation = (eye + b * k + c * (k @ k)) @ translation
    elif mode != "SO3xR3":
        raise ValueError(f"camera pose mode must be SO3xR3 or SE3, got {mode!r}")
    top = torch.cat([matrix, translation[:, None]], 1)
    return torch.cat([top, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=tangent.dtype)])


def rotation_angle_degrees(rotation: Tensor) -> float:
    """The angle in degrees of the rotation matrix [3, 3] (0 for the identity): atan2 of its sine
    (from the skew part) and cosine (from the trace), exact near 0 where arccos of the trace alone
    loses small angles to rounding (0.02 degrees in float32)."""
    matrix = rotation.double()
    skew_part = matrix - matrix.T
    sine = torch.stack([skew_part[2, 1], skew_part[0, 2], skew_part[1, 0]]).norm() / 2
    cosine = (torch.trace(matrix) - 1) / 2
    return math.degrees(float(torch.atan2(sine, cosine)))


class PoseCorrections(nn.Module):
    """One learned 6-vector per training view (zeros: the poses as given), one tensor each so Adam
    leaves the views a step does not see alone.

    The translation is learned in units of `scene_scale` (the scene's radius), so one learning rate
    suits scenes of any size.
    """

    scene_scale: Tensor

    def __init__(
        self, views: int, scene_scale: float, mode: str = "SO3xR3", lr: float = 1e-2, weight_decay: float = 0.0
    ):
        super().__init__()
        if mode not in ("SO3xR3", "SE3"):
            raise ValueError(f"camera pose mode must be SO3xR3 or SE3, got {mode!r}")
        self.corrections = nn.ParameterList(nn.Parameter(torch.zeros(6)) for _ in range(views))
        self.register_buffer("scene_scale", torch.tensor(float(scene_scale)))
        self.mode, self.lr, self.weight_decay = mode, lr, weight_decay
        self.run_length = 1
        """Steps of the run (Pipeline.set_run_length), over which the learning rate decays."""

    @classmethod
    def from_state_dict(cls, state: dict[str, Tensor], prefix: str = "poses.") -> "PoseCorrections | None":
        """An empty module shaped like the one saved under `prefix` (None when there is none); the
        mode does not matter for a model that only renders (held-out views are not corrected)."""
        views = sum(1 for key in state if key.startswith(f"{prefix}corrections."))
        if f"{prefix}scene_scale" not in state:
            return None
        return cls(views, float(state[f"{prefix}scene_scale"]))

    def __len__(self) -> int:
        return len(self.corrections)

    def correction(self, view: int) -> Tensor:
        """The rigid motion [4, 4] that training view `view`'s camera-to-world is multiplied by."""
        tangent = self.corrections[view]
        scaled = torch.cat([tangent[:3] * self.scene_scale, tangent[3:]])
        return pose_exp(scaled, self.mode)

    def refine(self, camera: Camera, view: int) -> Camera:
        """Training view `view`'s camera with its refined pose (differentiable in the correction)."""
        return replace(camera, c2w=camera.c2w.float() @ self.correction(view))

    def parameter_groups(self) -> list[dict]:
        return [
            {"name": "camera_poses", "params": list(self.corrections), "lr": self.lr, "weight_decay": self.weight_decay}
        ]

    def learning_rate(self, group_name: str, step: int, base_lr: float) -> float:
        """Exponential decay from `base_lr` to FINAL_LR_SHARE of it at the run's last step."""
        progress = min(max(step / max(self.run_length, 1), 0.0), 1.0)
        return base_lr * FINAL_LR_SHARE**progress

    @torch.no_grad()
    def report(self, cameras: list[Camera], names: list[str]) -> dict:
        """What OUT/refined_poses.json holds: per training view its pose as given, its refined pose
        (camera-to-world, OpenCV axes) and the size of the correction."""
        views = {}
        for index, (camera, name) in enumerate(zip(cameras, names, strict=True)):
            correction = self.correction(index)
            views[name] = {
                "c2w_given": camera.c2w.tolist(),
                "c2w_refined": (camera.c2w.float() @ correction).tolist(),
                "rotation_degrees": rotation_angle_degrees(correction[:3, :3]),
                "translation": float(correction[:3, 3].norm()),
            }
        return {"mode": self.mode, "axes": "OpenCV camera-to-world", "views": views}


def refinement_wanted(config: CameraOptConfig, poses: str | None, differentiable_pose: bool, backbone: str) -> bool:
    """Whether a run refines its training poses: --camera-opt on/off as given, auto where the data's
    `poses` (scene.metadata["poses"]) come from structure from motion and the backbone passes
    gradients to the pose."""
    if config.camera_opt == "on" and not differentiable_pose:
        raise FlagError(
            f"--camera-opt on: the backbone {backbone!r} renders without gradients to the camera pose "
            "(its differentiable_pose is False), so poses cannot be refined; pass --camera-opt off"
        )
    if config.camera_opt == "auto":
        return poses == STRUCTURE_FROM_MOTION and differentiable_pose
    return config.camera_opt == "on"


def build_pose_corrections(
    config: CameraOptConfig, scene, scene_scale: float, differentiable_pose: bool, backbone: str
) -> PoseCorrections | None:
    """The pose corrections of a training run on `scene` (SceneData), or None when poses are not refined."""
    if not refinement_wanted(config, scene.metadata.get("poses"), differentiable_pose, backbone):
        return None
    return PoseCorrections(
        len(scene.train), scene_scale, config.camera_opt_mode, config.camera_opt_lr, config.camera_opt_weight_decay
    )
