"""Rigid motions of Gaussians, for pose refinement through a projection that takes the pose as a constant.

The C++ projection returns no gradient for the world-to-camera matrix. Rendering with a world-to-camera
W' = W @ D is the same as rendering, with W, the Gaussians moved by the rigid motion D (means D m,
rotations R_D R): both put every Gaussian at the same place in the camera. Moving the Gaussians is
torch, so the gradient reaches D, and through it the pose. View-dependent colour is not moved: it is
evaluated in the world with the refined camera's centre (GaussianBackbone._visible_raw_colors).
"""

from dataclasses import replace

import torch
from torch import Tensor

from backbones.gs.reference import QUAT_NORM_MIN2
from mono_hdr_plugin.core.cameras import Camera


def rotation_to_quaternion(rotation: Tensor) -> Tensor:
    """Unit quaternion (w, x, y, z) [4] of the rotation matrix [3, 3] (Shepperd's method: the
    largest of w, x, y, z is found first, so no branch divides by a small number)."""
    r = rotation
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    largest = int(torch.argmax(torch.stack([trace, r[0, 0], r[1, 1], r[2, 2]]).detach()))
    if largest == 0:
        s = 2 * torch.sqrt(1 + trace)
        q = torch.stack([s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s])
    elif largest == 1:
        s = 2 * torch.sqrt(1 + r[0, 0] - r[1, 1] - r[2, 2])
        q = torch.stack([(r[2, 1] - r[1, 2]) / s, s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s])
    elif largest == 2:
        s = 2 * torch.sqrt(1 + r[1, 1] - r[0, 0] - r[2, 2])
        q = torch.stack([(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s])
    else:
        s = 2 * torch.sqrt(1 + r[2, 2] - r[0, 0] - r[1, 1])
        q = torch.stack([(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4])
    return q / q.norm()


def quaternion_product(left: Tensor, right: Tensor) -> Tensor:
    """Hamilton product left * right of quaternions (w, x, y, z), broadcast over leading dimensions:
    the rotation of `right` followed by that of `left`."""
    w1, x1, y1, z1 = left.unbind(-1)
    w2, x2, y2, z2 = right.unbind(-1)
    return torch.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        -1,
    )


def move_gaussians(means: Tensor, quats: Tensor, motion: Tensor) -> tuple[Tensor, Tensor]:
    """Means [N, 3] and rotations [N, 4] of Gaussians moved by the rigid motion [4, 4]; scales,
    opacities and colours do not change. A quaternion the rasteriser reads as the identity (zero,
    or too short) is moved as the identity, so it stays the same rotation."""
    motion = motion.to(means.dtype)
    rotation, translation = motion[:3, :3], motion[:3, 3]
    moved_means = means @ rotation.T + translation
    norm2 = (quats * quats).sum(-1, keepdim=True)
    usable = (norm2 > QUAT_NORM_MIN2) & torch.isfinite(norm2)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype)
    moved_quats = quaternion_product(
        rotation_to_quaternion(rotation).to(quats.dtype), torch.where(usable, quats, identity)
    )
    return moved_means, moved_quats


def camera_as_world_motion(camera: Camera) -> tuple[Camera, Tensor]:
    """For a camera whose pose requires grad: the same camera with the pose as a constant, and the
    motion D [4, 4] of the world (identity in value, differentiable in the pose) with which rendering
    the moved Gaussians through the constant camera renders the Gaussians through `camera`."""
    fixed = replace(camera, c2w=camera.c2w.detach())
    return fixed, fixed.c2w @ camera.w2c
