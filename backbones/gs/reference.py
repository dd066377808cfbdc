"""Plain-torch twins of the C++ rasteriser: slow, obvious, differentiable by autograd.

Two twins define what the kernel must compute:
- tiled (`project_gaussians_torch`, `bin_tiles_torch`, `rasterize_tiles_torch`): the same
  16 x 16 tiles, per-tile depth order and screen boxes as the kernel, one tile at a time;
- dense (`rasterize_dense_torch`): every pixel against every Gaussian in global depth
  order, no tiles and no boxes; for tiny scenes only ([H*W, N] memory).
Both follow the 3DGS rules: alpha = min(0.99, opacity * exp(power)), skip alpha < 1/255 or
power > 0, stop before transmittance falls below 1e-4. They agree because a Gaussian's box
covers every pixel where its alpha can reach 1/255.
"""

import math

import torch
from torch import Tensor

TILE_SIZE = 16
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
TRANSMITTANCE_MIN = 1e-4
DILATION = 0.3
QUAT_NORM_MIN2 = 1e-20


def quaternion_to_rotation(quats: Tensor) -> Tensor:
    """Rotation matrices [N, 3, 3] from quaternions [N, 4] (w, x, y, z, any norm; zero -> identity)."""
    norm2 = (quats * quats).sum(-1, keepdim=True)
    usable = (norm2 > QUAT_NORM_MIN2) & torch.isfinite(norm2)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype)
    safe = torch.where(usable, quats, identity)
    w, x, y, z = (safe / safe.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(-1, 3, 3)


def _project(means, quats, scales, viewmat, fx, fy, cx, cy, width, height):
    """EWA projection of every Gaussian, no culling: camera means, 2D means, 2D covariances."""
    t = means @ viewmat[:3, :3].T + viewmat[:3, 3]
    tz = t[:, 2]
    rotation = quaternion_to_rotation(quats)
    m = rotation * scales[:, None, :]
    sigma3 = m @ m.transpose(1, 2)
    # J at a mean clamped to 1.3 x the field of view, as 3DGS does
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    ux = (t[:, 0] / tz).clamp(-(cx / fx + 0.3 * tan_x), (width - cx) / fx + 0.3 * tan_x)
    uy = (t[:, 1] / tz).clamp(-(cy / fy + 0.3 * tan_y), (height - cy) / fy + 0.3 * tan_y)
    zero = torch.zeros_like(tz)
    jacobian = torch.stack([fx / tz, zero, -fx * ux / tz, zero, fy / tz, -fy * uy / tz], -1).reshape(-1, 2, 3)
    jw = jacobian @ viewmat[:3, :3]
    cov = jw @ sigma3 @ jw.transpose(1, 2)
    cov = cov + DILATION * torch.eye(2, dtype=cov.dtype)
    means2d = torch.stack([fx * t[:, 0] / tz + cx, fy * t[:, 1] / tz + cy], -1)
    return t, means2d, cov


def project_gaussians_torch(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmat: Tensor,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    near: float,
) -> tuple[Tensor, ...]:
    """Torch twin of the kernel's projection, culling and compaction.

    means [N,3], quats [N,4] (w,x,y,z), scales [N,3] (linear), opacities [N] in (0, 1),
    viewmat [4,4] world-to-camera (OpenCV). Returns index [V] int64 (the visible rows,
    ascending), radii [N] int32 (ceil of 3 sigma, 0 = culled), and for the visible Gaussians
    means2d [V,2], conics [V,3] (a, b, c of the inverse 2D covariance), depths [V] and boxes
    [V,4] int32 (x0, y0, x1, y1, end-exclusive pixel ranges). Culled Gaussians get exactly zero
    gradients.
    """
    with torch.no_grad():  # decide who is visible on detached values, then differentiate only those
        t, means2d, cov = _project(means, quats, scales, viewmat, fx, fy, cx, cy, width, height)
        a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
        det = a * c - b * b
        conic = torch.stack([c / det, -b / det, a / det], -1)
        visible = (
            torch.isfinite(t).all(-1)
            & (t[:, 2] >= near)
            & (det > 0)
            & torch.isfinite(det)
            & torch.isfinite(conic).all(-1)
            & torch.isfinite(means2d).all(-1)
        )
        mid = 0.5 * (a + c)
        sigma = torch.sqrt(mid + torch.sqrt((mid * mid - det).clamp_min(0.1)))
        reach2 = 2.0 * torch.log(255.0 * opacities)
        extent = torch.sqrt(reach2.clamp_min(0)) * sigma
        x0 = torch.floor(means2d[:, 0] - extent).clamp(0, width)
        x1 = torch.ceil(means2d[:, 0] + extent).clamp(0, width)
        y0 = torch.floor(means2d[:, 1] - extent).clamp(0, height)
        y1 = torch.ceil(means2d[:, 1] + extent).clamp(0, height)
        visible &= (reach2 > 0) & (x0 < x1) & (y0 < y1) & torch.isfinite(sigma)
        index = visible.nonzero().squeeze(1)
        boxes = torch.stack([x0, y0, x1, y1], -1)[index].to(torch.int32)
        radii = torch.where(visible, torch.ceil(3.0 * sigma).clamp(max=1e9), 0).to(torch.int32)

    t, means2d, cov = _project(means[index], quats[index], scales[index], viewmat, fx, fy, cx, cy, width, height)
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = a * c - b * b
    return index, radii, means2d, torch.stack([c / det, -b / det, a / det], -1), t[:, 2], boxes


def tile_grid(width: int, height: int) -> tuple[int, int]:
    """Number of 16 x 16 tiles along x and y."""
    return math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)


def bin_tiles_torch(boxes: Tensor, depths: Tensor, width: int, height: int) -> tuple[Tensor, Tensor]:
    """Torch twin of the kernel's binning.

    boxes [N,4] int32, depths [N]. Returns tile_offsets [T+1] int32 and tile_ids [M] int32:
    tile t (row-major) holds tile_ids[tile_offsets[t]:tile_offsets[t+1]], sorted by depth,
    ties by index.
    """
    tiles_x, tiles_y = tile_grid(width, height)
    boxes = boxes.long()
    nonempty = (boxes[:, 0] < boxes[:, 2]) & (boxes[:, 1] < boxes[:, 3])
    first_tile_x, first_tile_y = boxes[:, 0] // TILE_SIZE, boxes[:, 1] // TILE_SIZE
    end_tile_x, end_tile_y = -(-boxes[:, 2] // TILE_SIZE), -(-boxes[:, 3] // TILE_SIZE)
    offsets, ids = [0], []
    for tile in range(tiles_x * tiles_y):
        tx, ty = tile % tiles_x, tile // tiles_x
        hit = nonempty & (first_tile_x <= tx) & (tx < end_tile_x) & (first_tile_y <= ty) & (ty < end_tile_y)
        members = hit.nonzero().squeeze(1)
        members = members[torch.argsort(depths[members].detach(), stable=True)]
        ids.append(members)
        offsets.append(offsets[-1] + members.numel())
    return (
        torch.tensor(offsets, dtype=torch.int32),
        torch.cat(ids).to(torch.int32) if ids else torch.zeros(0, dtype=torch.int32),
    )


def _composite(power: Tensor, opacities: Tensor, values: Tensor, allowed: Tensor) -> tuple[Tensor, Tensor]:
    """Front-to-back blending along dim 1 of power [P, K] (Gaussians in depth order).

    opacities [K], values [K, C], allowed [P, K] bool (pixel inside the Gaussian's box).
    Returns colours [P, C] and transmittance [P].
    """
    # power > 0 only arises from rounding and is skipped; clamping keeps exp and its gradient finite
    alpha = (opacities[None, :] * torch.exp(power.clamp(max=0))).clamp(max=ALPHA_MAX)
    alpha = torch.where(allowed & (power <= 0) & (alpha >= ALPHA_MIN), alpha, 0.0)
    # a Gaussian that would take T below 1e-4 ends the pixel: it and all behind it are skipped
    alpha = torch.where(torch.cumprod(1 - alpha, 1) >= TRANSMITTANCE_MIN, alpha, 0.0)
    transmittance_after = torch.cumprod(1 - alpha, 1)
    transmittance_before = torch.cat([torch.ones_like(alpha[:, :1]), transmittance_after[:, :-1]], 1)
    return (alpha * transmittance_before) @ values, transmittance_after[:, -1]


def _power(means2d: Tensor, conics: Tensor, pixels: Tensor) -> Tensor:
    """Exponent of every Gaussian [K] at every pixel centre [P, 2]: [P, K]."""
    dx = means2d[None, :, 0] - pixels[:, None, 0]
    dy = means2d[None, :, 1] - pixels[:, None, 1]
    return -0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) - conics[:, 1] * dx * dy


def rasterize_tiles_torch(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    values: Tensor,
    boxes: Tensor,
    tile_offsets: Tensor,
    tile_ids: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Torch twin of the kernel's compositing, one tile at a time.

    means2d [N,2], conics [N,3], opacities [N], values [N,C], boxes [N,4], tile lists from
    `bin_tiles_torch`. Returns image [H,W,C] (black background) and alpha [H,W,1].
    """
    tiles_x, tiles_y = tile_grid(width, height)
    channels = values.shape[1]
    pixel_index, tile_colors, tile_transmittance = [], [], []
    for tile in range(tiles_x * tiles_y):
        start, end = int(tile_offsets[tile]), int(tile_offsets[tile + 1])
        if start == end:
            continue
        x0, y0 = (tile % tiles_x) * TILE_SIZE, (tile // tiles_x) * TILE_SIZE
        ys, xs = torch.meshgrid(
            torch.arange(y0, min(y0 + TILE_SIZE, height)), torch.arange(x0, min(x0 + TILE_SIZE, width)), indexing="ij"
        )
        xs, ys = xs.reshape(-1), ys.reshape(-1)
        ids = tile_ids[start:end].long()
        box = boxes[ids].long()
        inside = (
            (xs[:, None] >= box[:, 0])
            & (xs[:, None] < box[:, 2])
            & (ys[:, None] >= box[:, 1])
            & (ys[:, None] < box[:, 3])
        )
        pixels = torch.stack([xs, ys], -1).to(means2d.dtype) + 0.5
        colors, transmittance = _composite(
            _power(means2d[ids], conics[ids], pixels), opacities[ids], values[ids], inside
        )
        pixel_index.append(ys * width + xs)
        tile_colors.append(colors)
        tile_transmittance.append(transmittance)
    image = values.new_zeros(height * width, channels)
    transmittance = values.new_ones(height * width)
    if pixel_index:
        index = torch.cat(pixel_index)
        image = image.index_copy(0, index, torch.cat(tile_colors))
        transmittance = transmittance.index_copy(0, index, torch.cat(tile_transmittance))
    return image.reshape(height, width, channels), (1 - transmittance).reshape(height, width, 1)


def rasterize_dense_torch(
    means2d: Tensor, conics: Tensor, opacities: Tensor, values: Tensor, depths: Tensor, width: int, height: int
) -> tuple[Tensor, Tensor]:
    """Brute-force twin: every pixel against every (visible) Gaussian, in depth order.

    Same arguments as `rasterize_tiles_torch` but no tiles or boxes. Memory is [H*W, V]:
    tiny scenes only. Returns image [H,W,C] and alpha [H,W,1].
    """
    order = torch.argsort(depths.detach(), stable=True)
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    pixels = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1).to(means2d.dtype) + 0.5
    power = _power(means2d[order], conics[order], pixels)
    colors, transmittance = _composite(power, opacities[order], values[order], torch.ones_like(power, dtype=torch.bool))
    return colors.reshape(height, width, -1), (1 - transmittance).reshape(height, width, 1)
