"""Differentiable CPU rasteriser for 3D Gaussians: projection, tile binning, compositing.

Two steps, so one projection serves several renders of different channels:

    projected = project_gaussians(means, quats, scales, opacities, camera)
    image, alpha = rasterize(projected, values)        # values [V, C]: the visible Gaussians

Projection culls: everything after it works on the V visible Gaussians only (projected.index
says which of the N they are), so per-Gaussian work elsewhere (colours, converters) can skip
the culled ones too. `backend="kernel"` (default) runs the C++ extension (built on first use);
`backend="torch"` runs the plain-torch twin in `reference.py`, which defines the same result.
"""

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from backbones.gs import reference
from backbones.gs._extension import load_extension
from mono_hdr_plugin.core.cameras import Camera

Backend = Literal["kernel", "torch"]


@dataclass
class ProjectedGaussians:
    """Screen-space Gaussians of one camera: the V visible ones of N, binned into 16 x 16 tiles.

    index [V] int64: which of the N Gaussians are visible (ascending). radii [N] int32: ceil of
    3 sigma in pixels for every Gaussian, 0 when culled. For the visible ones: means2d [V,2]
    pixel coordinates (pixel centres at integer + 0.5), whose gradient is the screen-space
    gradient densification reads; conics [V,3] (a, b, c) of the inverse 2D covariance; depths
    [V] camera z; opacities [V]; boxes [V,4] int32 pixel ranges (x0, y0, x1, y1), end-exclusive;
    tile_offsets [T+1] and tile_ids [M] int32: the depth-sorted rows (into V) of each tile.
    width, height: the rendered image's size; frame: (width, height) of the whole image when that is a
    crop of it (Camera.crop), else None.
    """

    index: Tensor
    radii: Tensor
    means2d: Tensor
    conics: Tensor
    depths: Tensor
    opacities: Tensor
    boxes: Tensor
    tile_offsets: Tensor
    tile_ids: Tensor
    width: int
    height: int
    backend: Backend
    frame: tuple[int, int] | None = None


def _camera_arguments(camera: Camera) -> tuple:
    if camera.pixels is not None:
        raise ValueError("the Gaussian rasteriser renders whole images: pass a camera with pixels=None")
    return (
        float(camera.fx),
        float(camera.fy),
        float(camera.cx),
        float(camera.cy),
        int(camera.width),
        int(camera.height),
        float(camera.near),
    )


class _ProjectKernel(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, intrinsics):
        index, radii, means2d, conics, depths, boxes = load_extension().project_forward(
            means, quats, scales, opacities, viewmat, *intrinsics
        )
        ctx.save_for_backward(means, quats, scales, viewmat, index)
        ctx.intrinsics = intrinsics
        ctx.mark_non_differentiable(index, radii, boxes)
        return index, radii, means2d, conics, depths, boxes

    @staticmethod
    def backward(ctx, _v_index, _v_radii, v_means2d, v_conics, v_depths, _v_boxes):
        means, quats, scales, viewmat, index = ctx.saved_tensors
        v_means, v_quats, v_scales = load_extension().project_backward(
            means,
            quats,
            scales,
            viewmat,
            index,
            *ctx.intrinsics,
            v_means2d.contiguous(),
            v_conics.contiguous(),
            v_depths.contiguous(),
        )
        return v_means, v_quats, v_scales, None, None, None


class _RasterizeKernel(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, values, boxes, tile_offsets, tile_ids, width, height):
        image, transmittance, last = load_extension().rasterize_forward(
            means2d, conics, opacities, values, boxes, tile_offsets, tile_ids, width, height
        )
        ctx.save_for_backward(means2d, conics, opacities, values, boxes, tile_offsets, tile_ids, transmittance, last)
        return image, (1 - transmittance).unsqueeze(-1)

    @staticmethod
    def backward(ctx, v_image, v_alpha):
        (means2d, conics, opacities, values, boxes, tile_offsets, tile_ids, transmittance, last) = ctx.saved_tensors
        v_means2d, v_conics, v_opacities, v_values = load_extension().rasterize_backward(
            means2d,
            conics,
            opacities,
            values,
            boxes,
            tile_offsets,
            tile_ids,
            transmittance,
            last,
            v_image.contiguous(),
            v_alpha.reshape(transmittance.shape).contiguous(),
        )
        return v_means2d, v_conics, v_opacities, v_values, None, None, None, None, None


def _as_float32(name: str, tensor: Tensor, shape_tail: tuple[int, ...]) -> Tensor:
    if tensor.shape[1:] != shape_tail or tensor.dim() != 1 + len(shape_tail):
        raise ValueError(f"{name} must have shape [N, {', '.join(map(str, shape_tail))}], got {tuple(tensor.shape)}")
    if tensor.device.type != "cpu":
        raise ValueError(f"{name} is on {tensor.device}: the CPU rasteriser needs CPU tensors")
    return tensor.float().contiguous()


def _cut_to_crop(projection: tuple, camera: Camera) -> tuple:
    """A whole-image projection (index, radii, means2d, conics, depths, boxes) cut to a crop camera's
    image: the Gaussians whose box meets the crop, their screen positions and boxes in the crop's pixels.

    A crop is projected through its whole image's camera (Camera.uncropped) and cut afterwards, so every
    footprint is the whole image's: 3DGS evaluates the projection's Jacobian at the mean clamped to 1.3 x
    the field of view, and the crop's field of view would clamp Gaussians just outside the crop that
    reach into it, which the whole image does not (tests/gs/test_gs_regions.py). Gaussians are projected
    in O(N); the rasterising, which costs the pixels, sees the crop's Gaussians and pixels only."""
    if camera.frame is None:
        return projection
    index, radii, means2d, conics, depths, boxes = projection
    left, top = camera.frame.left, camera.frame.top
    shift = torch.tensor([left, top, left, top], dtype=torch.int32)
    limit = torch.tensor([camera.width, camera.height, camera.width, camera.height], dtype=torch.int32)
    cut = torch.minimum(torch.maximum(boxes - shift, torch.zeros_like(boxes)), limit)
    meets = (cut[:, 0] < cut[:, 2]) & (cut[:, 1] < cut[:, 3])
    keep = meets.nonzero().squeeze(1)
    radii = radii.clone()
    radii[index[~meets]] = 0  # off the crop: not visible in this step, as culled Gaussians are
    offset = torch.tensor([float(left), float(top)], dtype=means2d.dtype)
    return index[keep], radii, means2d[keep] - offset, conics[keep], depths[keep], cut[keep].contiguous()


def check_backend(backend: str) -> None:
    if backend not in ("kernel", "torch"):
        raise ValueError(f"backend must be 'kernel' or 'torch', got {backend!r}")


def project_gaussians(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, camera: Camera, backend: Backend = "kernel"
) -> ProjectedGaussians:
    """Project 3D Gaussians into `camera` (EWA, 0.3 px^2 dilation), cull, and bin the visible ones.

    means [N,3] world positions; quats [N,4] rotations (w, x, y, z), any norm, zero = identity;
    scales [N,3] standard deviations along the local axes (already activated, >= 0);
    opacities [N] in [0, 1] (already activated). Gaussians behind the near plane, with a
    degenerate or non-finite footprint, or whose alpha cannot reach 1/255 inside the image
    are culled (radii 0, not in `index`, no gradient). Differentiable w.r.t. means, quats and
    scales through means2d, conics and depths, and w.r.t. opacities through `rasterize`.
    """
    check_backend(backend)
    n = means.shape[0]
    means = _as_float32("means", means, (3,))
    quats = _as_float32("quats", quats, (4,))
    scales = _as_float32("scales", scales, (3,))
    if opacities.shape != (n,) or quats.shape[0] != n or scales.shape[0] != n:
        raise ValueError(
            f"means, quats, scales, opacities must share N={n}; got "
            f"{quats.shape[0]}, {scales.shape[0]}, {tuple(opacities.shape)}"
        )
    opacities = opacities.float()
    viewmat = camera.w2c.float().contiguous()
    if camera.pixels is not None:
        _camera_arguments(camera)  # refuses pixel batches
    intrinsics = _camera_arguments(camera.uncropped())
    if backend == "kernel":
        projection = _ProjectKernel.apply(means, quats, scales, opacities.detach().contiguous(), viewmat, intrinsics)
    else:
        projection = reference.project_gaussians_torch(means, quats, scales, opacities.detach(), viewmat, *intrinsics)
    index, radii, means2d, conics, depths, boxes = _cut_to_crop(projection, camera)
    if backend == "kernel":
        tile_offsets, tile_ids = load_extension().bin_tiles(boxes, depths.detach(), camera.width, camera.height)
    else:
        tile_offsets, tile_ids = reference.bin_tiles_torch(boxes, depths, camera.width, camera.height)
    return ProjectedGaussians(
        index,
        radii,
        means2d,
        conics,
        depths,
        opacities[index].contiguous(),
        boxes,
        tile_offsets,
        tile_ids,
        camera.width,
        camera.height,
        backend,
        camera.frame_size if camera.frame is not None else None,
    )


def rasterize(projected: ProjectedGaussians, values: Tensor) -> tuple[Tensor, Tensor]:
    """Composite per-Gaussian `values` [V, C] (any C; row i belongs to projected.index[i]) front
    to back over a black background.

    Returns image [H, W, C] and alpha [H, W, 1] (1 - final transmittance). Differentiable
    w.r.t. values, projected.means2d, projected.conics and projected.opacities. To render
    depth, pass projected.depths[:, None] as (part of) the values.
    """
    visible = projected.index.shape[0]
    if values.dim() != 2 or values.shape[0] != visible:
        raise ValueError(f"values must have shape [V={visible}, C] (the visible Gaussians), got {tuple(values.shape)}")
    args = (
        projected.means2d,
        projected.conics,
        projected.opacities,
        values.float().contiguous(),
        projected.boxes,
        projected.tile_offsets,
        projected.tile_ids,
        projected.width,
        projected.height,
    )
    if projected.backend == "kernel":
        return _RasterizeKernel.apply(*args)
    return reference.rasterize_tiles_torch(*args)


def render_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    values: Tensor,
    camera: Camera,
    backend: Backend = "kernel",
) -> tuple[Tensor, Tensor, ProjectedGaussians]:
    """project_gaussians + rasterize of values [N, C] given for every Gaussian: image [H,W,C],
    alpha [H,W,1] and the projection."""
    if values.dim() != 2 or values.shape[0] != means.shape[0]:
        raise ValueError(f"values must have shape [N={means.shape[0]}, C], got {tuple(values.shape)}")
    projected = project_gaussians(means, quats, scales, opacities, camera, backend)
    image, alpha = rasterize(projected, values[projected.index])
    return image, alpha, projected
