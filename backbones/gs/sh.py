"""Real spherical harmonics up to degree 3, in the 3DGS basis and coefficient order."""

import torch
from torch import Tensor

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of coefficients per channel for SH `degree` (1, 4, 9 or 16)."""
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"SH degree must be 0, 1, 2 or 3, got {degree}")
    return (degree + 1) ** 2


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """DC coefficient [..., 3] whose evaluation (+0.5) gives colour `rgb` [..., 3]."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(dc: Tensor) -> Tensor:
    """Inverse of rgb_to_sh: DC coefficient [..., 3] -> colour [..., 3]."""
    return dc * SH_C0 + 0.5


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate SH of `degree` in unit directions.

    coeffs: [N, K, C] with K >= (degree + 1)^2 (extra coefficients are ignored).
    dirs: [N, 3] unit view directions (camera centre -> Gaussian mean).
    Returns [N, C], without the +0.5 offset 3DGS adds afterwards.
    """
    needed = num_sh_bases(degree)
    if coeffs.shape[-2] < needed:
        raise ValueError(f"coeffs has {coeffs.shape[-2]} SH bases, degree {degree} needs {needed}")
    result = SH_C0 * coeffs[:, 0]
    if degree == 0:
        return result
    x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
    result = result - SH_C1 * y * coeffs[:, 1] + SH_C1 * z * coeffs[:, 2] - SH_C1 * x * coeffs[:, 3]
    if degree == 1:
        return result
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    result = (
        result
        + SH_C2[0] * xy * coeffs[:, 4]
        + SH_C2[1] * yz * coeffs[:, 5]
        + SH_C2[2] * (2.0 * zz - xx - yy) * coeffs[:, 6]
        + SH_C2[3] * xz * coeffs[:, 7]
        + SH_C2[4] * (xx - yy) * coeffs[:, 8]
    )
    if degree == 2:
        return result
    return (
        result
        + SH_C3[0] * y * (3.0 * xx - yy) * coeffs[:, 9]
        + SH_C3[1] * xy * z * coeffs[:, 10]
        + SH_C3[2] * y * (4.0 * zz - xx - yy) * coeffs[:, 11]
        + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * coeffs[:, 12]
        + SH_C3[4] * x * (4.0 * zz - xx - yy) * coeffs[:, 13]
        + SH_C3[5] * z * (xx - yy) * coeffs[:, 14]
        + SH_C3[6] * x * (xx - 3.0 * yy) * coeffs[:, 15]
    )


def view_directions(means: Tensor, camera_center: Tensor) -> Tensor:
    """Unit directions [N, 3] from `camera_center` [3] to `means` [N, 3] (zero-safe)."""
    offset = means - camera_center.to(means)
    return offset / offset.norm(dim=-1, keepdim=True).clamp_min(1e-12)


class _ShKernel(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sh_dc, sh_rest, means, index, center, degree):
        from backbones.gs._extension import load_extension  # the twin needs no build

        ctx.save_for_backward(sh_dc, sh_rest, means, index, center)
        ctx.degree = degree
        return load_extension().sh_forward(sh_dc, sh_rest, means, index, center, degree)

    @staticmethod
    def backward(ctx, v_colors):
        from backbones.gs._extension import load_extension

        sh_dc, sh_rest, means, index, center = ctx.saved_tensors
        v_dc, v_rest, v_means = load_extension().sh_backward(
            sh_dc, sh_rest, means, index, center, ctx.degree, v_colors.contiguous()
        )
        # The colours see the means only through the direction mean - centre, so the centre's gradient
        # is minus the sum of the means' (pose refinement moves the centre).
        v_center = -v_means.sum(0) if ctx.needs_input_grad[4] else None
        return v_dc, v_rest, v_means, None, v_center, None


def visible_colors(
    degree: int,
    sh_dc: Tensor,
    sh_rest: Tensor,
    means: Tensor,
    index: Tensor,
    camera_center: Tensor,
    backend: str = "kernel",
) -> Tensor:
    """SH colours [V, 3] (without the +0.5) of the Gaussians `index` [V] seen from `camera_center`.

    sh_dc [N, 1, 3], sh_rest [N, K - 1, 3], means [N, 3]. Differentiable w.r.t. the
    coefficients, the means and the camera centre (through the view direction); culled Gaussians
    cost nothing.
    `backend="kernel"` runs the C++ extension, "torch" this module's `eval_sh` (its twin).
    """
    num_sh_bases(degree)
    if sh_rest.shape[1] + 1 < num_sh_bases(degree):
        raise ValueError(f"degree {degree} needs {num_sh_bases(degree)} SH bases, got {sh_rest.shape[1] + 1}")
    if backend == "kernel":
        return _ShKernel.apply(
            sh_dc.float().contiguous(),
            sh_rest.float().contiguous(),
            means.float().contiguous(),
            index.contiguous(),
            camera_center.float().contiguous(),
            degree,
        )
    coeffs = torch.cat([sh_dc[index], sh_rest[index]], 1)
    return eval_sh(degree, coeffs, view_directions(means[index], camera_center))
