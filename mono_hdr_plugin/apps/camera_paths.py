"""Cameras that are not in the dataset: the viewer's, and paths for videos.

The viewer (viser) reports a camera with OpenCV axes (x right, y down, z forward) as the
rotation world_from_camera in a (w, x, y, z) quaternion, a position, a vertical field of view
and the canvas aspect; the project's Camera is OpenCV camera-to-world with focal lengths in
pixels, so the conversion is the rotation matrix, the position, and fy = H / (2 tan(fov / 2)).
"""

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.training.evaluation import first_per_camera

PathKind = Literal["dataset", "interpolate", "spiral"]


@dataclass(frozen=True)
class ViewerCamera:
    """A camera as a viser client sends it.

    wxyz: world_from_camera rotation (OpenCV camera axes) as a unit quaternion (w, x, y, z).
    position: camera centre in world coordinates.
    fov: vertical field of view in radians. aspect: canvas width / height.
    """

    wxyz: tuple[float, float, float, float]
    position: tuple[float, float, float]
    fov: float
    aspect: float


def camera_from_viewer(view: ViewerCamera, height: int, near: float, far: float) -> Camera:
    """The project's Camera for a viewer camera, rendered `height` pixels high at its aspect."""
    if not (0 < view.fov < math.pi):
        raise ValueError(f"viewer field of view must be in (0, pi) radians, got {view.fov}")
    width = max(1, round(height * view.aspect))
    w, x, y, z = view.wxyz
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.from_numpy(Rotation.from_quat([x, y, z, w]).as_matrix())
    c2w[:3, 3] = torch.tensor(view.position, dtype=torch.float64)
    focal = 0.5 * height / math.tan(0.5 * view.fov)
    return Camera(
        c2w=c2w.float(),
        fx=focal,
        fy=focal,
        cx=0.5 * width,
        cy=0.5 * height,
        width=width,
        height=height,
        near=near,
        far=far,
    )


def viewer_from_camera(camera: Camera) -> ViewerCamera:
    """The viewer camera that sees what `camera` sees (its vertical field of view and aspect)."""
    x, y, z, w = Rotation.from_matrix(camera.c2w[:3, :3].double().numpy()).as_quat()
    center = camera.center
    return ViewerCamera(
        wxyz=(float(w), float(x), float(y), float(z)),
        position=(float(center[0]), float(center[1]), float(center[2])),
        fov=2.0 * math.atan(0.5 * camera.height / camera.fy),
        aspect=camera.width / camera.height,
    )


def scene_up(cameras: list[Camera]) -> torch.Tensor:
    """The world's up direction as the cameras hold it: the mean of their -y axes, unit length."""
    up = -torch.stack([c.c2w[:3, 1].float() for c in cameras]).mean(0)
    return up / up.norm().clamp_min(1e-12)


def focus_point(scene: SceneData, cameras: list[Camera]) -> torch.Tensor:
    """The point the cameras look at: nearest to all optical axes in the least-squares sense; the
    centre of the scene bounds when the axes are (nearly) parallel or it lies behind the cameras."""
    fallback = 0.5 * (scene.bounds_min.float() + scene.bounds_max.float())
    if len(cameras) < 2:
        return fallback
    system, rhs = torch.zeros(3, 3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
    for camera in cameras:
        axis = camera.c2w[:3, 2].double()
        projector = torch.eye(3, dtype=torch.float64) - torch.outer(axis, axis)
        system += projector
        rhs += projector @ camera.center.double()
    if torch.linalg.cond(system) > 1e4:
        return fallback
    point = torch.linalg.solve(system, rhs).float()
    ahead = [float((point - c.center.float()) @ c.c2w[:3, 2].float()) for c in cameras]
    return point if min(ahead) > 0 else fallback


def _with_pose(template: Camera, c2w: torch.Tensor, near: float, far: float) -> Camera:
    return Camera(
        c2w=c2w.float(),
        fx=template.fx,
        fy=template.fy,
        cx=template.cx,
        cy=template.cy,
        width=template.width,
        height=template.height,
        near=near,
        far=far,
    )


def dataset_path(views: list[View], frames: int | None) -> list[Camera]:
    """The dataset's cameras in its order; `frames` of them, evenly spread, when fewer are asked for."""
    cameras = [view.camera for view in first_per_camera(views)]
    if frames is None or frames >= len(cameras):
        return cameras
    return [cameras[round(i * (len(cameras) - 1) / max(frames - 1, 1))] for i in range(frames)]


def interpolate_path(views: list[View], frames: int) -> list[Camera]:
    """`frames` cameras gliding through the dataset's cameras in its order: positions and
    intrinsics linear, rotations spherical-linear (slerp) between neighbours."""
    keys = [view.camera for view in first_per_camera(views)]
    if len(keys) < 2:
        raise ValueError("--path interpolate needs at least two cameras in the split; use --path spiral")
    times = np.linspace(0.0, len(keys) - 1, frames)
    rotations = Slerp(
        np.arange(len(keys)), Rotation.from_matrix(np.stack([k.c2w[:3, :3].double().numpy() for k in keys]))
    )(times).as_matrix()
    near, far = min(k.near for k in keys), max(k.far for k in keys)
    path = []
    for time, rotation in zip(times, rotations, strict=True):
        index = min(int(time), len(keys) - 2)
        share = float(time - index)
        a, b = keys[index], keys[index + 1]
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3] = torch.from_numpy(rotation)
        c2w[:3, 3] = (1 - share) * a.center.double() + share * b.center.double()
        path.append(
            Camera(
                c2w=c2w.float(),
                fx=(1 - share) * a.fx + share * b.fx,
                fy=(1 - share) * a.fy + share * b.fy,
                cx=(1 - share) * a.cx + share * b.cx,
                cy=(1 - share) * a.cy + share * b.cy,
                width=a.width,
                height=a.height,
                near=near,
                far=far,
            )
        )
    return path


def spiral_path(scene: SceneData, views: list[View], frames: int, rotations: float = 2.0) -> list[Camera]:
    """`frames` cameras looking at the scene's focus point.

    Cameras that surround their focus (a ring rig) orbit it once at their mean distance, their
    height swinging between the lowest and highest camera. Cameras that face one way (a
    forward-facing capture) circle `rotations` times around their mean position in its image
    plane, with radii from the spread of the cameras, as LLFF's spiral does.
    """
    cameras = [view.camera for view in first_per_camera(views)]
    template = cameras[0]
    near, far = min(c.near for c in cameras), max(c.far for c in cameras)
    focus, up = focus_point(scene, cameras), scene_up(cameras)
    centres = torch.stack([c.center.float() for c in cameras])
    distances = (centres - focus).norm(dim=-1)
    mean_centre = centres.mean(0)
    angles = torch.linspace(0.0, 2 * math.pi, frames + 1)[:-1]
    if (mean_centre - focus).norm() < 0.5 * distances.mean():
        heights = (centres - focus) @ up
        start = centres[0] - focus - heights[0] * up
        side = torch.linalg.cross(up, start)
        planar = (distances.mean() ** 2 - heights.mean() ** 2).clamp_min(1e-12).sqrt()
        start, side = planar * start / start.norm(), planar * side / side.norm().clamp_min(1e-12)
        low, high = heights.min(), heights.max()
        eyes = [
            focus
            + torch.cos(a) * start
            + torch.sin(a) * side
            + (0.5 * (low + high) + 0.5 * (high - low) * torch.sin(2 * a)) * up
            for a in angles
        ]
    else:
        forward = (focus - mean_centre) / (focus - mean_centre).norm()
        right = torch.linalg.cross(forward, up)
        right = right / right.norm()
        down = torch.linalg.cross(forward, right)
        offsets = centres - mean_centre
        reach = 0.05 * float((focus - mean_centre).norm())
        radius_x = max(float(torch.quantile((offsets @ right).abs(), 0.9)), reach)
        radius_y = max(float(torch.quantile((offsets @ down).abs(), 0.9)), reach)
        eyes = [
            mean_centre
            + radius_x * torch.cos(rotations * a) * right
            + radius_y * torch.sin(rotations * a) * down
            + reach * torch.sin(0.5 * rotations * a) * forward
            for a in angles
        ]
    return [_with_pose(template, look_at(eye, focus, up), near, far) for eye in eyes]


def camera_path(kind: str, scene: SceneData, views: list[View], frames: int | None) -> list[Camera]:
    """The cameras of `--path KIND` (dataset, interpolate, spiral) through `views`."""
    if frames is not None and frames < 1:
        raise ValueError(f"--frames must be at least 1, got {frames}")
    if kind == "dataset":
        return dataset_path(views, frames)
    if kind == "interpolate":
        return interpolate_path(views, frames or 120)
    if kind == "spiral":
        return spiral_path(scene, views, frames or 120)
    raise ValueError(f"unknown --path {kind!r}; choose dataset, interpolate or spiral")
