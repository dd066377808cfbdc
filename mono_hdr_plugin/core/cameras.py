"""Pinhole cameras in one convention: OpenCV (x right, y down, z forward), camera-to-world.

Loaders convert every other convention (OpenGL/Blender, LLFF, COLMAP world-to-camera) into
this one, so backbones never see another.
"""

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

# OpenGL/Blender cameras look along -z with y up; flipping y and z gives OpenCV axes.
OPENGL_TO_OPENCV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))


@dataclass(frozen=True)
class Frame:
    """The whole image a crop camera's image was cut from: its size, and the crop's offset in it."""

    width: int
    height: int
    left: int
    top: int


@dataclass(frozen=True)
class Camera:
    """One pinhole camera.

    c2w: [4, 4] camera-to-world, OpenCV axes. fx, fy, cx, cy in pixels (pixel centres at
    integer + 0.5). near/far bound the scene along the viewing ray for volume renderers.
    pixels: optional [N, 2] (x, y) pixel-centre coordinates; when set, a backbone renders
    only these pixels (ray batches) and images come back as [N, C] instead of [H, W, C].
    frame: the whole image when this camera renders a crop of it (`crop`; region training), None for a
    whole image. What is defined on the whole image reads it: 3DGS projects through the whole camera
    (`uncropped`; its footprints clamp to the whole field of view) and scales its densification gradient
    by `frame_size`.
    """

    c2w: Tensor
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    near: float = 0.01
    far: float = 100.0
    pixels: Tensor | None = None
    frame: "Frame | None" = None

    def __post_init__(self):
        if tuple(self.c2w.shape) != (4, 4):
            raise ValueError(f"camera pose must be 4x4, got shape {tuple(self.c2w.shape)}")
        if not torch.isfinite(self.c2w).all():
            raise ValueError("camera pose contains NaN or Inf: check the poses file")
        rotation = self.c2w[:3, :3].double()
        if not torch.allclose(rotation @ rotation.T, torch.eye(3, dtype=torch.float64), atol=1e-3):
            raise ValueError(
                "camera rotation is not orthonormal: check the poses file "
                "(scaled or sheared rotations are not supported)"
            )
        if not (0 < self.fx < math.inf and 0 < self.fy < math.inf):
            raise ValueError(f"focal lengths must be positive and finite, got fx={self.fx}, fy={self.fy}")
        if not (math.isfinite(self.cx) and math.isfinite(self.cy)):
            raise ValueError(f"the principal point must be finite, got cx={self.cx}, cy={self.cy}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not (0 <= self.near <= self.far < math.inf):
            raise ValueError(f"need 0 <= near <= far (finite), got near={self.near}, far={self.far}")

    @property
    def w2c(self) -> Tensor:
        rotation, translation = self.c2w[:3, :3], self.c2w[:3, 3]
        w2c = torch.eye(4, dtype=self.c2w.dtype)
        w2c[:3, :3] = rotation.T
        w2c[:3, 3] = -rotation.T @ translation
        return w2c

    @property
    def center(self) -> Tensor:
        return self.c2w[:3, 3]

    @property
    def intrinsics(self) -> Tensor:
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def output_shape(self) -> tuple[int, ...]:
        """Leading shape of a rendered image: (H, W) or (N,) for a pixel batch."""
        return (self.height, self.width) if self.pixels is None else (self.pixels.shape[0],)

    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height) of the whole image this camera's image is (a crop of)."""
        return (self.width, self.height) if self.frame is None else (self.frame.width, self.frame.height)

    def with_pixels(self, pixels: Tensor | None) -> "Camera":
        return replace(self, pixels=pixels)

    def crop(self, left: int, top: int, width: int, height: int) -> "Camera":
        """The camera whose image is pixels [top, top + height) x [left, left + width) of this one's:
        the principal point shifted by the offset, the same pose and focal lengths, `frame` the whole
        image (a crop of a crop is a crop of the same whole image)."""
        if min(left, top) < 0 or min(width, height) <= 0:
            raise ValueError(f"a crop needs a non-negative offset and a positive size, got {left, top, width, height}")
        if left + width > self.width or top + height > self.height:
            raise ValueError(f"crop {width}x{height} at ({left}, {top}) leaves the {self.width}x{self.height} image")
        outer = self.frame or Frame(self.width, self.height, 0, 0)
        return replace(
            self,
            cx=self.cx - left,
            cy=self.cy - top,
            width=width,
            height=height,
            pixels=None,
            frame=Frame(outer.width, outer.height, outer.left + left, outer.top + top),
        )

    def uncropped(self) -> "Camera":
        """The whole image's camera of a crop camera; a whole-image camera itself."""
        if self.frame is None:
            return self
        frame = self.frame
        return replace(
            self,
            cx=self.cx + frame.left,
            cy=self.cy + frame.top,
            width=frame.width,
            height=frame.height,
            pixels=None,
            frame=None,
        )

    def scaled(self, factor: float) -> "Camera":
        """The same camera with the image resized by `factor` (0.5 halves the resolution)."""
        if self.frame is not None:
            raise ValueError("a crop camera cannot be scaled: scale the whole camera, then crop it")
        return replace(
            self,
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=self.cx * factor,
            cy=self.cy * factor,
            width=round(self.width * factor),
            height=round(self.height * factor),
            pixels=None,
        )

    def pixel_centers(self) -> Tensor:
        """[N, 2] (x, y) pixel centres of the rendered pixels, row-major for a full image."""
        if self.pixels is not None:
            return self.pixels
        ys, xs = torch.meshgrid(
            torch.arange(self.height, dtype=torch.float32) + 0.5,
            torch.arange(self.width, dtype=torch.float32) + 0.5,
            indexing="ij",
        )
        return torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)

    def rays(self) -> tuple[Tensor, Tensor]:
        """World-space ray origins and unit directions, each [*output_shape, 3]."""
        pixels = self.pixel_centers()
        directions_cam = torch.stack(
            [(pixels[:, 0] - self.cx) / self.fx, (pixels[:, 1] - self.cy) / self.fy, torch.ones(pixels.shape[0])], -1
        )
        directions = directions_cam @ self.c2w[:3, :3].T.float()
        directions = directions / directions.norm(dim=-1, keepdim=True)
        origins = self.c2w[:3, 3].float().expand_as(directions)
        shape = (*self.output_shape, 3)
        return origins.reshape(shape), directions.reshape(shape)

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """World points [N, 3] -> (pixel coordinates [N, 2], camera-space depth [N])."""
        w2c = self.w2c.to(points.dtype)
        cam = points @ w2c[:3, :3].T + w2c[:3, 3]
        depth = cam[:, 2]
        x = self.fx * cam[:, 0] / depth + self.cx
        y = self.fy * cam[:, 1] / depth + self.cy
        return torch.stack([x, y], -1), depth


def focal_from_fov(fov_x: float, width: int) -> float:
    """Focal length in pixels from a horizontal field of view in radians (Blender's camera_angle_x)."""
    return 0.5 * width / torch.tan(torch.tensor(0.5 * fov_x)).item()


WORLD_UP = torch.tensor([0.0, 0.0, 1.0])


def look_at(eye: Tensor, target: Tensor, up: Tensor = WORLD_UP) -> Tensor:
    """OpenCV camera-to-world [4, 4] of a camera at `eye` looking at `target` (world z up)."""
    forward = target - eye
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, up)
    if right.norm() < 1e-6:  # looking straight along `up`: pick any perpendicular
        right = torch.linalg.cross(forward, torch.tensor([1.0, 0.0, 0.0]))
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    c2w = torch.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w
