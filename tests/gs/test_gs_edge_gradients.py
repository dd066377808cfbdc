"""Rasteriser gradients where the projection takes its special branches.

Gaussians outside the field of view (the Jacobian is evaluated at the mean clamped to 1.3 x the
field of view, so its derivative changes form), behind and straddling the near plane, with
nearly degenerate covariances, and with radii far larger than the image. Three checks per case,
through the public API only (`project_gaussians`, `render_gaussians`), so they hold for any
correct kernel:
- finite differences of the kernel's own projection (means2d, conics, depths) against its
  backward pass, coordinate by coordinate;
- the kernel against the plain-torch twin: projection and image values and gradients;
- closed-form values of the clamped projection.
Each case is checked on its own, so an error in one Gaussian cannot hide under the gradient
scale of the others.
"""

import math

import pytest
import torch

from backbones.gs.rasterizer import project_gaussians, render_gaussians
from mono_hdr_plugin.core.cameras import Camera, look_at

WIDTH, HEIGHT, FX, FY, CX, CY, NEAR = 40, 32, 36.0, 37.8, 20.7, 15.6, 0.05
# camera-space x/z and y/z beyond which the Jacobian is clamped: the image edge plus 0.3 x half the field of view
LIMIT_RIGHT = (WIDTH - CX) / FX + 0.3 * 0.5 * WIDTH / FX
LIMIT_LEFT = CX / FX + 0.3 * 0.5 * WIDTH / FX
LIMIT_DOWN = (HEIGHT - CY) / FY + 0.3 * 0.5 * HEIGHT / FY
LIMIT_UP = CY / FY + 0.3 * 0.5 * HEIGHT / FY


def edge_camera() -> Camera:
    return Camera(
        look_at(torch.tensor([0.0, -4.0, 0.0]), torch.zeros(3)),
        fx=FX,
        fy=FY,
        cx=CX,
        cy=CY,
        width=WIDTH,
        height=HEIGHT,
        near=NEAR,
    )


def to_world(camera: Camera, t: list[float]) -> torch.Tensor:
    """A camera-space point (x right, y down, z forward) in world coordinates."""
    return camera.c2w[:3, :3] @ torch.tensor(t) + camera.c2w[:3, 3]


# name: (camera-space mean, scales, quaternion (w, x, y, z) in world axes, opacity)
EDGE_CASES = {
    "right-of-view-x-clamped": ([2.7, 0.3, 3.0], [0.6, 0.5, 0.4], [0.9, 0.2, -0.3, 0.1], 0.9),
    "left-of-view-x-clamped": ([-2.8, -0.2, 3.0], [0.5, 0.7, 0.4], [0.7, -0.1, 0.4, 0.3], 0.85),
    "below-view-y-clamped": ([0.2, 2.1, 3.0], [0.4, 0.6, 0.5], [0.8, 0.3, 0.1, -0.4], 0.9),
    "beyond-corner-x-and-y-clamped": ([2.4, -1.9, 3.0], [0.8, 0.6, 0.7], [0.6, 0.2, 0.5, -0.2], 0.95),
    "far-outside-x-clamped-reaching-in": ([6.0, 0.4, 3.0], [2.0, 1.5, 1.8], [0.9, -0.2, 0.1, 0.3], 0.9),
    "straddling-near-plane": ([0.01, -0.005, 0.06], [0.3, 0.2, 0.25], [0.9, 0.1, 0.2, 0.3], 0.7),
    "needle": ([-0.3, 0.2, 2.5], [0.5, 1e-3, 1e-3], [0.6, 0.5, -0.3, 0.4], 0.9),
    "disk-seen-edge-on": (
        [0.4, -0.3, 2.0],
        [0.4, 0.4, 1e-6],
        [math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0],
        0.9,
    ),
    "radius-far-beyond-image": ([0.05, 0.02, 0.3], [30.0, 30.0, 0.01], [0.5, 0.5, 0.5, 0.5], 0.5),
}
CULLED_CASES = {
    "between-eye-and-near-plane": ([0.0, 0.0, 0.04], [0.2, 0.2, 0.2], [1.0, 0.0, 0.0, 0.0], 0.9),
    "behind-camera": ([0.1, 0.0, -1.0], [0.5, 0.5, 0.5], [1.0, 0.0, 0.0, 0.0], 0.9),
}


def gaussians(camera: Camera, cases: list[tuple]) -> dict[str, torch.Tensor]:
    return {
        "means": torch.stack([to_world(camera, case[0]) for case in cases]),
        "scales": torch.tensor([case[1] for case in cases]),
        "quats": torch.tensor([case[2] for case in cases]),
        "opacities": torch.tensor([case[3] for case in cases]),
    }


def projection_loss(projected, weights: torch.Tensor, conic_scale: torch.Tensor) -> torch.Tensor:
    """A fixed weighted sum of every projected quantity, each term of order one (float64)."""
    terms = torch.cat(
        [
            projected.means2d.double() / 100.0,
            projected.conics.double() / conic_scale,
            projected.depths.double()[:, None],
        ],
        1,
    )
    return (terms * weights[: terms.shape[0]]).sum()


def projection_gradients(scene: dict, camera: Camera, backend: str, weights, conic_scale):
    leaves = {k: scene[k].clone().requires_grad_() for k in ("means", "quats", "scales")}
    projected = project_gaussians(
        leaves["means"], leaves["quats"], leaves["scales"], scene["opacities"], camera, backend=backend
    )
    projection_loss(projected, weights, conic_scale).backward()
    return projected, {k: v.grad for k, v in leaves.items()}


def loss_weights(rows: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(rows, 6, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) + 0.5


def conic_scale_of(scene: dict, camera: Camera) -> torch.Tensor:
    """|conic| of each row at the unperturbed point, so every conic term of the loss is of order one."""
    with torch.no_grad():
        projected = project_gaussians(scene["means"], scene["quats"], scene["scales"], scene["opacities"], camera)
    return projected.conics.double().abs().clamp_min(1e-6)


@pytest.mark.parametrize("case", sorted(EDGE_CASES))
class TestEdgeCase:
    def test_is_visible_and_exercises_its_branch(self, case):
        camera = edge_camera()
        t, scales, *_ = EDGE_CASES[case]
        scene = gaussians(camera, [EDGE_CASES[case]])
        projected = project_gaussians(scene["means"], scene["quats"], scene["scales"], scene["opacities"], camera)
        assert projected.radii[0] > 0, "the case must be rendered, or it tests nothing"
        ux, uy = t[0] / t[2], t[1] / t[2]
        clamped = not (-LIMIT_LEFT <= ux <= LIMIT_RIGHT and -LIMIT_UP <= uy <= LIMIT_DOWN)
        assert clamped == ("clamped" in case)
        if "straddling" in case:
            assert t[2] - 3 * max(scales) < NEAR < t[2]

    def test_kernel_projection_matches_finite_differences(self, case):
        """Central differences of the kernel's forward pass, one coordinate at a time."""
        camera = edge_camera()
        scene = gaussians(camera, [EDGE_CASES[case]])
        conic_scale = conic_scale_of(scene, camera)
        projected, gradients = projection_gradients(scene, camera, "kernel", loss_weights(1), conic_scale)
        depth = EDGE_CASES[case][0][2]
        # scales step multiplicatively (the gradient compared is s dL/ds): an additive step small
        # enough for a 1e-3 scale would move its covariance by less than float32 resolves
        steps = {"means": 1e-3 * depth, "quats": 1e-3, "scales": 1e-2}
        for name, step in steps.items():
            numeric = torch.zeros(scene[name].shape[1], dtype=torch.float64)
            for index in range(scene[name].shape[1]):
                values = []
                for sign in (1, -1):
                    moved = {k: v.clone() for k, v in scene.items()}
                    if name == "scales":
                        moved[name][0, index] *= math.exp(sign * step)
                    else:
                        moved[name][0, index] += sign * step
                    with torch.no_grad():
                        shifted = project_gaussians(
                            moved["means"], moved["quats"], moved["scales"], moved["opacities"], camera
                        )
                        assert shifted.radii[0] > 0
                        values.append(projection_loss(shifted, loss_weights(1), conic_scale).item())
                if name == "scales":
                    numeric[index] = (values[0] - values[1]) / (2 * step)
                else:
                    moved_by = float(scene[name][0, index] + step) - float(scene[name][0, index] - step)
                    numeric[index] = (values[0] - values[1]) / moved_by
            analytic = gradients[name][0].double()
            if name == "scales":
                analytic = analytic * scene["scales"][0].double()
            scale = float(analytic.abs().max().clamp_min(numeric.abs().max()))
            torch.testing.assert_close(
                analytic,
                numeric,
                rtol=2e-2,
                atol=5e-3 * scale,
                msg=lambda message, name=name: f"{case}: gradient of {name}\n{message}",
            )

    def test_kernel_projection_matches_torch_twin(self, case):
        camera = edge_camera()
        scene = gaussians(camera, [EDGE_CASES[case]])
        conic_scale = conic_scale_of(scene, camera)
        kernel, kernel_grads = projection_gradients(scene, camera, "kernel", loss_weights(1), conic_scale)
        twin, twin_grads = projection_gradients(scene, camera, "torch", loss_weights(1), conic_scale)
        assert torch.equal(kernel.radii, twin.radii)
        torch.testing.assert_close(kernel.means2d, twin.means2d, rtol=1e-5, atol=1e-4)
        torch.testing.assert_close(kernel.conics, twin.conics, rtol=1e-4, atol=1e-7)
        torch.testing.assert_close(kernel.depths, twin.depths)
        for name, want in twin_grads.items():
            scale = float(want.abs().max().clamp_min(1e-12))
            torch.testing.assert_close(
                kernel_grads[name],
                want,
                rtol=1e-3,
                atol=1e-4 * scale,
                msg=lambda message, name=name: f"{case}: gradient of {name}\n{message}",
            )

    def test_kernel_image_gradients_match_torch_twin(self, case):
        """The whole render (projection and compositing) over an ordinary Gaussian behind it."""
        camera = edge_camera()
        background = ([0.1, 0.1, 6.0], [1.5, 1.2, 0.3], [1.0, 0.0, 0.0, 0.0], 0.6)
        scene = gaussians(camera, [EDGE_CASES[case], background])
        scene["values"] = torch.tensor([[0.9, 0.2, 0.4], [0.1, 0.6, 0.8]])
        weights = torch.rand(HEIGHT, WIDTH, 4, generator=torch.Generator().manual_seed(5)) - 0.3
        results = {}
        for backend in ("kernel", "torch"):
            leaves = {k: v.clone().requires_grad_() for k, v in scene.items()}
            image, alpha, _ = render_gaussians(
                leaves["means"],
                leaves["quats"],
                leaves["scales"],
                leaves["opacities"],
                leaves["values"],
                camera,
                backend=backend,
            )
            ((image * weights[..., :3]).sum() + (alpha[..., 0] * weights[..., 3]).sum()).backward()
            results[backend] = image, alpha, {k: v.grad for k, v in leaves.items()}
        (image_k, alpha_k, grads_k), (image_t, alpha_t, grads_t) = results["kernel"], results["torch"]
        assert alpha_t.max() > 0.05, "the case must reach the image"
        torch.testing.assert_close(image_k, image_t, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(alpha_k, alpha_t, rtol=1e-5, atol=1e-5)
        for name, want in grads_t.items():
            for row in range(2):  # each Gaussian against its own gradient scale
                got = grads_k[name][row]
                assert torch.isfinite(got).all(), f"{case}: {name}[{row}] not finite"
                scale = float(want[row].abs().max().clamp_min(1e-9))
                torch.testing.assert_close(
                    got,
                    want[row],
                    rtol=1e-3,
                    atol=2e-4 * scale,
                    msg=lambda message, name=name, row=row: f"{case}: gradient of {name}[{row}]\n{message}",
                )


@pytest.mark.parametrize("case", sorted(CULLED_CASES))
@pytest.mark.parametrize("backend", ["kernel", "torch"])
def test_behind_the_near_plane_is_culled_with_zero_gradient(case, backend):
    camera = edge_camera()
    visible = EDGE_CASES["right-of-view-x-clamped"]
    scene = gaussians(camera, [CULLED_CASES[case], visible])
    scene["values"] = torch.tensor([[1.0, 0.5, 0.2], [0.3, 0.3, 0.9]])
    leaves = {k: v.clone().requires_grad_() for k, v in scene.items()}
    image, alpha, projected = render_gaussians(
        leaves["means"],
        leaves["quats"],
        leaves["scales"],
        leaves["opacities"],
        leaves["values"],
        camera,
        backend=backend,
    )
    (image.sum() + alpha.sum()).backward()
    assert projected.radii.tolist()[0] == 0 and projected.radii.tolist()[1] > 0
    for name, leaf in leaves.items():
        assert torch.isfinite(leaf.grad).all(), name
        assert not leaf.grad[0].any(), f"{name}: a culled Gaussian got gradient"
        assert leaf.grad[1].any(), f"{name}: the visible Gaussian got none"


class TestClampedProjectionValues:
    """An isotropic Gaussian (sigma s) at camera-space (x, y, z): its 2D covariance is
    s^2 J J^T + 0.3 I with J = [[fx, 0, -fx u], [0, fy, -fy v]] / z, where u, v are x / z, y / z
    clamped to the limits, while the 2D mean stays at the unclamped projection."""

    @pytest.mark.parametrize(
        "t", [[2.7, 0.3, 3.0], [-2.8, -0.2, 3.0], [0.2, 2.1, 3.0], [2.4, -1.9, 3.0], [0.3, -0.2, 2.0]]
    )
    def test_covariance_and_mean(self, t):
        camera = edge_camera()
        s = 0.8
        x, y, z = t
        u = min(max(x / z, -LIMIT_LEFT), LIMIT_RIGHT)
        v = min(max(y / z, -LIMIT_UP), LIMIT_DOWN)
        a = s * s * FX * FX / (z * z) * (1 + u * u) + 0.3
        b = s * s * FX * FY / (z * z) * u * v
        c = s * s * FY * FY / (z * z) * (1 + v * v) + 0.3
        det = a * c - b * b
        projected = project_gaussians(
            to_world(camera, t)[None],
            torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
            torch.full((1, 3), s),
            torch.tensor([0.99]),
            camera,
        )
        assert projected.radii[0] > 0
        torch.testing.assert_close(
            projected.conics[0].double(),
            torch.tensor([c / det, -b / det, a / det], dtype=torch.float64),
            rtol=1e-4,
            atol=1e-7,
        )
        torch.testing.assert_close(
            projected.means2d[0].double(),
            torch.tensor([FX * x / z + CX, FY * y / z + CY], dtype=torch.float64),
            rtol=1e-6,
            atol=1e-4,
        )
        torch.testing.assert_close(projected.depths[0].double(), torch.tensor(z, dtype=torch.float64))
