"""Differentiable CPU rasteriser for 3D Gaussians: projection, tile binning, compositing.

Two steps, so one projection serves several renders of different channels:

    projected = project_gaussians(means, quats, scales, opacities, camera)
    image, alpha = rasterize(projected, values)        # values [N, C], any C

`backend="kernel"` (default) runs the C++ extension (built on first use); `backend="torch"`
runs the plain-torch twin in `reference.py`, which defines the same result.
"""

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from backbones.gs import reference
from backbones.gs._extension import load_extension
from mono_hdr_plugin.cameras import Camera

Backend = Literal["kernel", "torch"]


@dataclass
class ProjectedGaussians:
    """Screen-space Gaussians of one camera, binned into 16 x 16 tiles.

    means2d [N,2] pixel coordinates (pixel centres at integer + 0.5); its gradient is the
    screen-space gradient densification reads. conics [N,3] (a, b, c) of the inverse 2D
    covariance; depths [N] camera z; opacities [N]; radii [N] int32 (ceil of 3 sigma, 0 when
    culled); boxes [N,4] int32 pixel ranges (x0, y0, x1, y1), end-exclusive;
    tile_offsets [T+1] and tile_ids [M] int32: the depth-sorted Gaussians of each tile.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    opacities: Tensor
    radii: Tensor
    boxes: Tensor
    tile_offsets: Tensor
    tile_ids: Tensor
    width: int
    height: int
    backend: Backend


def _camera_arguments(camera: Camera) -> tuple:
    if camera.pixels is not None:
        raise ValueError("the Gaussian rasteriser renders whole images: pass a camera with pixels=None")
    return (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy),
            int(camera.width), int(camera.height), float(camera.near))


class _ProjectKernel(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, intrinsics):
        means2d, conics, depths, radii, boxes = load_extension().project_forward(
            means, quats, scales, opacities, viewmat, *intrinsics)
        ctx.save_for_backward(means, quats, scales, viewmat, radii)
        ctx.intrinsics = intrinsics
        ctx.mark_non_differentiable(radii, boxes)
        return means2d, conics, depths, radii, boxes

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_radii, _v_boxes):
        means, quats, scales, viewmat, radii = ctx.saved_tensors
        v_means, v_quats, v_scales = load_extension().project_backward(
            means, quats, scales, viewmat, radii, *ctx.intrinsics,
            v_means2d.contiguous(), v_conics.contiguous(), v_depths.contiguous())
        return v_means, v_quats, v_scales, None, None, None


class _RasterizeKernel(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, values, boxes, tile_offsets, tile_ids, width, height):
        image, transmittance, last = load_extension().rasterize_forward(
            means2d, conics, opacities, values, boxes, tile_offsets, tile_ids, width, height)
        ctx.save_for_backward(means2d, conics, opacities, values, boxes, tile_offsets, tile_ids,
                              transmittance, last)
        return image, (1 - transmittance).unsqueeze(-1)

    @staticmethod
    def backward(ctx, v_image, v_alpha):
        (means2d, conics, opacities, values, boxes, tile_offsets, tile_ids,
         transmittance, last) = ctx.saved_tensors
        v_means2d, v_conics, v_opacities, v_values = load_extension().rasterize_backward(
            means2d, conics, opacities, values, boxes, tile_offsets, tile_ids, transmittance, last,
            v_image.contiguous(), v_alpha.reshape(transmittance.shape).contiguous())
        return v_means2d, v_conics, v_opacities, v_values, None, None, None, None, None


def _as_float32(name: str, tensor: Tensor, shape_tail: tuple[int, ...]) -> Tensor:
    if tensor.shape[1:] != shape_tail or tensor.dim() != 1 + len(shape_tail):
        raise ValueError(f"{name} must have shape [N, {', '.join(map(str, shape_tail))}], "
                         f"got {tuple(tensor.shape)}")
    if tensor.device.type != "cpu":
        raise ValueError(f"{name} is on {tensor.device}: the CPU rasteriser needs CPU tensors")
    return tensor.float().contiguous()


def project_gaussians(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                      camera: Camera, backend: Backend = "kernel") -> ProjectedGaussians:
    """Project 3D Gaussians into `camera` (EWA, 0.3 px^2 dilation) and bin them into tiles.

    means [N,3] world positions; quats [N,4] rotations (w, x, y, z), any norm, zero = identity;
    scales [N,3] standard deviations along the local axes (already activated, >= 0);
    opacities [N] in [0, 1] (already activated). Gaussians behind the near plane, with a
    degenerate or non-finite footprint, or whose alpha cannot reach 1/255 inside the image
    are culled (radii 0, no gradient). Differentiable w.r.t. means, quats and scales through
    means2d, conics and depths; opacities reach the gradient through `rasterize`.
    """
    n = means.shape[0]
    means = _as_float32("means", means, (3,))
    quats = _as_float32("quats", quats, (4,))
    scales = _as_float32("scales", scales, (3,))
    if opacities.shape != (n,) or quats.shape[0] != n or scales.shape[0] != n:
        raise ValueError(f"means, quats, scales, opacities must share N={n}; got "
                         f"{quats.shape[0]}, {scales.shape[0]}, {tuple(opacities.shape)}")
    opacities = opacities.float().contiguous()
    viewmat = camera.w2c.float().contiguous()
    intrinsics = _camera_arguments(camera)
    if backend == "kernel":
        means2d, conics, depths, radii, boxes = _ProjectKernel.apply(
            means, quats, scales, opacities.detach(), viewmat, intrinsics)
        tile_offsets, tile_ids = load_extension().bin_tiles(boxes, depths.detach(), camera.width, camera.height)
    elif backend == "torch":
        means2d, conics, depths, radii, boxes = reference.project_gaussians_torch(
            means, quats, scales, opacities.detach(), viewmat, *intrinsics)
        tile_offsets, tile_ids = reference.bin_tiles_torch(boxes, depths, camera.width, camera.height)
    else:
        raise ValueError(f"backend must be 'kernel' or 'torch', got {backend!r}")
    return ProjectedGaussians(means2d, conics, depths, opacities, radii, boxes, tile_offsets, tile_ids,
                              camera.width, camera.height, backend)


def rasterize(projected: ProjectedGaussians, values: Tensor) -> tuple[Tensor, Tensor]:
    """Composite per-Gaussian `values` [N, C] (any C) front to back over a black background.

    Returns image [H, W, C] and alpha [H, W, 1] (1 - final transmittance). Differentiable
    w.r.t. values, projected.means2d, projected.conics and projected.opacities. To render
    depth, pass projected.depths[:, None] as (part of) the values.
    """
    n = projected.means2d.shape[0]
    if values.dim() != 2 or values.shape[0] != n:
        raise ValueError(f"values must have shape [N={n}, C], got {tuple(values.shape)}")
    args = (projected.means2d, projected.conics, projected.opacities, values.float().contiguous(),
            projected.boxes, projected.tile_offsets, projected.tile_ids, projected.width, projected.height)
    if projected.backend == "kernel":
        return _RasterizeKernel.apply(*args)
    return reference.rasterize_tiles_torch(*args)


def render_gaussians(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, values: Tensor,
                     camera: Camera, backend: Backend = "kernel") -> tuple[Tensor, Tensor, ProjectedGaussians]:
    """project_gaussians + rasterize: image [H,W,C], alpha [H,W,1] and the projection."""
    projected = project_gaussians(means, quats, scales, opacities, camera, backend)
    image, alpha = rasterize(projected, values)
    return image, alpha, projected
