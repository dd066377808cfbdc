"""C++ kernel against its plain-torch twins: values, gradients, hard cases, one class per step."""

import pytest
import torch
from gs_scenes import hard_gaussians, make_camera, pixel_weights, random_gaussians

from backbones.gs import reference
from backbones.gs.rasterizer import project_gaussians, rasterize, render_gaussians

PARAMS = ("means", "quats", "scales", "opacities", "values")


def render_with_grads(scene: dict, camera, backend: str):
    """Render, back-propagate a weighted loss on image, alpha and depth; return outputs and grads."""
    leaves = {k: scene[k].clone().requires_grad_() for k in PARAMS}
    projected = project_gaussians(
        leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], camera, backend=backend
    )
    projected.means2d.retain_grad()
    channels = leaves["values"].shape[1]
    values = torch.cat([leaves["values"][projected.index], projected.depths[:, None]], 1)
    image, alpha = rasterize(projected, values)
    weights = pixel_weights(camera.height, camera.width, channels + 2)
    loss = (image * weights[..., :-1]).sum() + (alpha * weights[..., -1:]).sum()
    loss.backward()
    grads = {k: leaves[k].grad for k in PARAMS}
    grads["means2d"] = projected.means2d.grad
    return image, alpha, projected, grads


def assert_grads_close(actual: dict, expected: dict, rtol: float = 1e-4):
    for name, want in expected.items():
        got = actual[name]
        assert torch.isfinite(got).all(), f"{name} gradient not finite"
        scale = want.abs().max().clamp_min(1e-6)
        torch.testing.assert_close(got, want, rtol=rtol, atol=rtol * float(scale), msg=f"gradient of {name}")


class TestProjectGaussians:
    def test_matches_torch_twin(self, camera):
        scene = random_gaussians(300, seed=1)
        kernel = project_gaussians(*(scene[k] for k in PARAMS[:4]), camera, backend="kernel")
        twin = project_gaussians(*(scene[k] for k in PARAMS[:4]), camera, backend="torch")
        assert kernel.radii.gt(0).sum() > 100, "scene should be mostly visible"
        assert torch.equal(kernel.radii, twin.radii)
        assert torch.equal(kernel.index, twin.index)
        assert torch.equal(kernel.index, kernel.radii.nonzero().squeeze(1))
        assert torch.equal(kernel.boxes, twin.boxes)
        torch.testing.assert_close(kernel.means2d, twin.means2d, rtol=1e-5, atol=1e-4)
        torch.testing.assert_close(kernel.conics, twin.conics, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(kernel.depths, twin.depths)

    def test_known_values(self):
        """An isotropic Gaussian on the optical axis lands on (cx, cy) with conic 1 / (s^2 f^2 / z^2 + 0.3)."""
        camera = make_camera(width=32, height=32)
        depth, sigma = 3.0, 0.05
        mean = camera.center + depth * camera.c2w[:3, 2]
        projected = project_gaussians(
            mean[None], torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), sigma), torch.tensor([0.9]), camera
        )
        torch.testing.assert_close(projected.means2d[0], torch.tensor([camera.cx, camera.cy]), rtol=0, atol=1e-4)
        torch.testing.assert_close(projected.depths[0], torch.tensor(depth), rtol=1e-6, atol=1e-5)
        var_x = (sigma * camera.fx / depth) ** 2 + 0.3
        var_y = (sigma * camera.fy / depth) ** 2 + 0.3
        torch.testing.assert_close(projected.conics[0], torch.tensor([1 / var_x, 0.0, 1 / var_y]), rtol=1e-5, atol=1e-6)

    def test_culls_hard_cases_without_nan(self, camera):
        scene = hard_gaussians(camera)
        projected = project_gaussians(*(scene[k] for k in PARAMS[:4]), camera)
        radii = projected.radii[40:]  # the hard rows follow 40 ordinary Gaussians
        culled = {
            3: "overflowing scale",
            4: "behind the camera",
            5: "at the eye",
            10: "opacity 1e-6",
            11: "opacity 0",
            12: "off-screen",
        }
        for row, why in culled.items():
            assert radii[row] == 0, why
        assert radii[0] > 0, "zero quaternion renders as unrotated"
        assert radii[1] > 0, "zero scale still has the 0.3 px^2 dilation"
        assert radii[7] > 0, "huge radius is kept (clipped to the image)"
        assert projected.means2d.shape[0] == projected.index.shape[0] == int((projected.radii > 0).sum())
        for name in ("means2d", "conics", "depths"):
            assert torch.isfinite(getattr(projected, name)).all(), name
        assert (projected.boxes[:, 2] <= camera.width).all() and (projected.boxes[:, 3] <= camera.height).all()

    def test_gradients_match_torch_twin_on_hard_cases(self, camera):
        scene = hard_gaussians(camera)
        _, _, _, kernel = render_with_grads(scene, camera, "kernel")
        _, _, _, twin = render_with_grads(scene, camera, "torch")
        assert_grads_close(kernel, twin)

    def test_rejects_bad_shapes(self, camera):
        scene = random_gaussians(5)
        with pytest.raises(ValueError, match="quats"):
            project_gaussians(scene["means"], scene["quats"][:, :3], scene["scales"], scene["opacities"], camera)
        with pytest.raises(ValueError, match="share N"):
            project_gaussians(scene["means"], scene["quats"], scene["scales"], scene["opacities"][:4], camera)
        with pytest.raises(ValueError, match="backend"):
            project_gaussians(*(scene[k] for k in PARAMS[:4]), camera, backend="cuda")


class TestBinTiles:
    @pytest.mark.parametrize("size", [(40, 32), (16, 16), (33, 17)])
    def test_matches_torch_twin(self, size):
        camera = make_camera(*size)
        scene = random_gaussians(200, seed=2)
        projected = project_gaussians(*(scene[k] for k in PARAMS[:4]), camera)
        offsets, ids = reference.bin_tiles_torch(projected.boxes, projected.depths, camera.width, camera.height)
        assert torch.equal(projected.tile_offsets, offsets)
        assert torch.equal(projected.tile_ids, ids)

    def test_tiles_sorted_front_to_back(self, camera):
        scene = random_gaussians(200, seed=3)
        projected = project_gaussians(*(scene[k] for k in PARAMS[:4]), camera)
        offsets = projected.tile_offsets.tolist()
        assert offsets[-1] == projected.tile_ids.numel() > 0
        for start, end in zip(offsets[:-1], offsets[1:]):
            depths = projected.depths[projected.tile_ids[start:end].long()]
            assert (depths[1:] >= depths[:-1]).all()


class TestRasterize:
    @pytest.mark.parametrize("channels", [1, 3, 6])
    @pytest.mark.parametrize("seed", [0, 1])
    def test_matches_torch_twin(self, camera, channels, seed):
        scene = random_gaussians(400, seed=seed, channels=channels)
        image_k, alpha_k, _, grads_k = render_with_grads(scene, camera, "kernel")
        image_t, alpha_t, _, grads_t = render_with_grads(scene, camera, "torch")
        assert alpha_t.max() > 0.9, "scene should cover some pixels fully"
        torch.testing.assert_close(image_k, image_t, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(alpha_k, alpha_t, rtol=1e-5, atol=1e-5)
        assert_grads_close(grads_k, grads_t)

    def test_hard_cases_match_and_stay_finite(self, camera):
        scene = hard_gaussians(camera, channels=6)
        image_k, alpha_k, _, grads_k = render_with_grads(scene, camera, "kernel")
        image_t, alpha_t, _, _ = render_with_grads(scene, camera, "torch")
        assert torch.isfinite(image_k).all() and torch.isfinite(alpha_k).all()
        assert alpha_k.max() <= 1.0
        torch.testing.assert_close(image_k, image_t, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(alpha_k, alpha_t, rtol=1e-5, atol=1e-5)
        for name, grad in grads_k.items():
            assert torch.isfinite(grad).all(), name

    def test_deep_stack_stops_at_transmittance_floor(self, camera):
        """A stack of wide, opaque Gaussians: pixels saturate after a few, the rest are skipped."""
        n = 30
        forward = camera.c2w[:3, 2]
        means = camera.center + (2.0 + 0.01 * torch.arange(n, dtype=torch.float32))[:, None] * forward
        scene = {
            "means": means,
            "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
            "scales": torch.full((n, 3), 5.0),
            "opacities": torch.full((n,), 0.95),
            "values": torch.rand(n, 3, generator=torch.Generator().manual_seed(0)),
        }
        image_k, alpha_k, _, grads_k = render_with_grads(scene, camera, "kernel")
        image_t, alpha_t, _, grads_t = render_with_grads(scene, camera, "torch")
        assert alpha_k.min() > 1 - 1e-3
        assert grads_t["values"][6:].abs().max() == 0, "Gaussians behind the floor get no gradient"
        assert grads_k["values"][6:].abs().max() == 0, "Gaussians behind the floor get no gradient"
        torch.testing.assert_close(image_k, image_t, rtol=1e-5, atol=1e-5)
        assert_grads_close(grads_k, grads_t)

    def test_channels_composite_independently(self, camera):
        """One 6-channel pass equals two 3-channel passes (LDR + HDR in one go)."""
        scene = random_gaussians(300, seed=4, channels=6)
        projected = project_gaussians(*(scene[k] for k in PARAMS[:4]), camera)
        values = scene["values"][projected.index]
        both, _ = rasterize(projected, values)
        first, _ = rasterize(projected, values[:, :3])
        second, _ = rasterize(projected, values[:, 3:])
        torch.testing.assert_close(both, torch.cat([first, second], -1), rtol=0, atol=1e-6)

    def test_gradients_repeat_bit_for_bit_on_several_threads(self):
        """Tiles of very uneven cost share Gaussians across threads; a schedule that hands tiles to
        whichever thread is free sums them in a different order each run (the old dynamic schedule
        differed here within a few runs)."""
        if torch.get_num_threads() < 2:
            pytest.skip("needs two threads")
        camera = make_camera(width=96, height=96)
        scene = random_gaussians(3000, seed=2, channels=6)
        scene["means"] = scene["means"] * torch.linspace(0.05, 1.0, 3000)[:, None]  # crowded centre tiles
        scene["scales"] = scene["scales"] * 4
        first = render_with_grads(scene, camera, "kernel")[3]
        for _ in range(6):
            again = render_with_grads(scene, camera, "kernel")[3]
            for name, grad in first.items():
                assert torch.equal(again[name], grad), f"gradient of {name} changed between runs"

    def test_empty_scene_is_black(self, camera):
        scene = random_gaussians(4)
        scene["means"] = scene["means"] - 100 * camera.c2w[:3, 2]  # all behind the camera
        image, alpha, projected = render_gaussians(*(scene[k] for k in PARAMS), camera)
        assert projected.tile_ids.numel() == 0
        assert image.abs().max() == 0 and alpha.abs().max() == 0

    def test_rejects_bad_values(self, camera):
        scene = random_gaussians(5)
        projected = project_gaussians(*(scene[k] for k in PARAMS[:4]), camera)
        with pytest.raises(ValueError, match="values"):
            rasterize(projected, scene["values"][:4])
        with pytest.raises(ValueError, match="values"):
            render_gaussians(*(scene[k] for k in PARAMS[:4]), scene["values"][:4], camera)
        with pytest.raises(ValueError, match="pixels=None"):
            project_gaussians(*(scene[k] for k in PARAMS[:4]), camera.with_pixels(torch.zeros(3, 2)))


class TestDenseTwin:
    @pytest.mark.parametrize("seed", [0, 5])
    def test_tiled_twin_matches_brute_force(self, seed):
        camera = make_camera(width=24, height=20)
        scene = random_gaussians(60, seed=seed, channels=4, dtype=torch.float64)
        viewmat = camera.w2c.double()
        args = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, camera.near)
        index, _, means2d, conics, depths, boxes = reference.project_gaussians_torch(
            scene["means"], scene["quats"], scene["scales"], scene["opacities"], viewmat, *args
        )
        offsets, ids = reference.bin_tiles_torch(boxes, depths, camera.width, camera.height)
        opacities, values = scene["opacities"][index], scene["values"][index]
        tiled, tiled_alpha = reference.rasterize_tiles_torch(
            means2d, conics, opacities, values, boxes, offsets, ids, camera.width, camera.height
        )
        dense, dense_alpha = reference.rasterize_dense_torch(
            means2d, conics, opacities, values, depths, camera.width, camera.height
        )
        assert dense_alpha.max() > 0.5
        torch.testing.assert_close(tiled, dense, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(tiled_alpha, dense_alpha, rtol=1e-10, atol=1e-10)


class TestGradcheck:
    def test_torch_twin_finite_differences(self):
        """float64 finite differences through projection and tiled compositing of a tiny scene."""
        camera = make_camera(width=12, height=10)
        scene = random_gaussians(5, seed=9, channels=2, dtype=torch.float64)
        scene["scales"] = scene["scales"] * 4
        scene["opacities"] = scene["opacities"].clamp(0.2, 0.8)
        viewmat = camera.w2c.double()
        args = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, camera.near)

        def render(means, quats, scales, opacities, values):
            index, _, means2d, conics, depths, boxes = reference.project_gaussians_torch(
                means, quats, scales, opacities, viewmat, *args
            )
            offsets, ids = reference.bin_tiles_torch(boxes, depths, camera.width, camera.height)
            return reference.rasterize_tiles_torch(
                means2d, conics, opacities[index], values[index], boxes, offsets, ids, camera.width, camera.height
            )

        inputs = tuple(scene[k].clone().requires_grad_() for k in PARAMS)
        assert render(*inputs)[1].max() > 0.3
        assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)

    def test_kernel_matches_float64_twin(self, camera):
        scene = random_gaussians(200, seed=6)
        _, _, _, kernel = render_with_grads(scene, camera, "kernel")
        scene64 = {k: v.double() for k, v in scene.items()}
        _, _, _, twin = render_with_grads_float64(scene64, camera)
        assert_grads_close(kernel, {k: v.float() for k, v in twin.items()}, rtol=1e-3)


def render_with_grads_float64(scene: dict, camera):
    """Float64 torch twin of render_with_grads (the public API computes in float32)."""
    leaves = {k: scene[k].clone().requires_grad_() for k in PARAMS}
    args = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, camera.near)
    index, radii, means2d, conics, depths, boxes = reference.project_gaussians_torch(
        leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], camera.w2c.double(), *args
    )
    means2d.retain_grad()
    offsets, ids = reference.bin_tiles_torch(boxes, depths, camera.width, camera.height)
    values = torch.cat([leaves["values"][index], depths[:, None]], 1)
    image, alpha = reference.rasterize_tiles_torch(
        means2d, conics, leaves["opacities"][index], values, boxes, offsets, ids, camera.width, camera.height
    )
    weights = pixel_weights(camera.height, camera.width, values.shape[1] + 1).double()
    ((image * weights[..., :-1]).sum() + (alpha * weights[..., -1:]).sum()).backward()
    grads = {k: leaves[k].grad for k in PARAMS}
    grads["means2d"] = means2d.grad
    return image, alpha, (radii, boxes), grads
