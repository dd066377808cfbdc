"""Spherical harmonics: the C++ kernel against its torch twin (values and gradients), known values."""

import pytest
import torch

from backbones.gs.sh import SH_C0, SH_C1, eval_sh, num_sh_bases, view_directions, visible_colors


def sh_scene(n: int = 300, degree: int = 3, seed: int = 0) -> dict:
    gen = torch.Generator().manual_seed(seed)
    bases = num_sh_bases(degree)
    return {
        "sh_dc": torch.randn(n, 1, 3, generator=gen),
        "sh_rest": torch.randn(n, bases - 1, 3, generator=gen) * 0.3,
        "means": torch.randn(n, 3, generator=gen) * 2,
        "center": torch.tensor([0.3, -4.0, 0.5]),
    }


def colors_with_grads(scene: dict, index: torch.Tensor, degree: int, backend: str):
    leaves = {k: scene[k].clone().requires_grad_() for k in ("sh_dc", "sh_rest", "means")}
    colors = visible_colors(
        degree, leaves["sh_dc"], leaves["sh_rest"], leaves["means"], index, scene["center"], backend=backend
    )
    weights = torch.rand(colors.shape, generator=torch.Generator().manual_seed(5)) - 0.4
    (colors * weights).sum().backward()
    # degree 0 does not depend on the view direction: the twin leaves no gradient at all
    return colors, {k: torch.zeros_like(v) if v.grad is None else v.grad for k, v in leaves.items()}


class TestVisibleColors:
    @pytest.mark.parametrize("degree", [0, 1, 2, 3])
    def test_kernel_matches_torch_twin(self, degree):
        scene = sh_scene()
        index = torch.arange(0, 300, 3)  # a third of the Gaussians are visible
        kernel, kernel_grads = colors_with_grads(scene, index, degree, "kernel")
        twin, twin_grads = colors_with_grads(scene, index, degree, "torch")
        assert kernel.shape == (100, 3)
        torch.testing.assert_close(kernel, twin, rtol=1e-5, atol=1e-5)
        for name, want in twin_grads.items():
            torch.testing.assert_close(kernel_grads[name], want, rtol=1e-4, atol=1e-5, msg=name)
            hidden = torch.ones(300, dtype=torch.bool)
            hidden[index] = False
            assert kernel_grads[name][hidden].abs().max() == 0, f"a culled Gaussian got a {name} gradient"

    def test_higher_degree_coefficients_ignored_below_their_degree(self):
        scene = sh_scene()
        index = torch.arange(300)
        _, grads = colors_with_grads(scene, index, 1, "kernel")
        assert grads["sh_rest"][:, 3:].abs().max() == 0
        assert grads["sh_rest"][:, :3].abs().max() > 0

    def test_known_values(self):
        """Degree 0 is C0 * dc; degree 1 adds -C1 y, C1 z, -C1 x times the first three rest bases."""
        scene = sh_scene(n=2, degree=1)
        scene["means"] = scene["center"] + torch.tensor([[0.0, 0.0, 2.0], [3.0, 0.0, 0.0]])
        index = torch.arange(2)
        dc, rest = scene["sh_dc"][:, 0], scene["sh_rest"]
        colors = visible_colors(1, scene["sh_dc"], rest, scene["means"], index, scene["center"])
        torch.testing.assert_close(colors[0], SH_C0 * dc[0] + SH_C1 * rest[0, 1])  # direction +z
        torch.testing.assert_close(colors[1], SH_C0 * dc[1] - SH_C1 * rest[1, 2])  # direction +x

    def test_mean_at_the_camera_centre_stays_finite(self):
        scene = sh_scene(n=4)
        scene["means"][1] = scene["center"]
        _, grads = colors_with_grads(scene, torch.arange(4), 3, "kernel")
        assert all(torch.isfinite(g).all() for g in grads.values())

    def test_rejects_too_few_coefficients(self):
        scene = sh_scene(degree=1)
        with pytest.raises(ValueError, match="SH bases"):
            visible_colors(2, scene["sh_dc"], scene["sh_rest"], scene["means"], torch.arange(3), scene["center"])

    def test_twin_gradcheck(self):
        """float64 finite differences through eval_sh and the view direction (kornia style)."""
        gen = torch.Generator().manual_seed(2)
        coeffs = torch.randn(4, 16, 2, generator=gen, dtype=torch.float64, requires_grad=True)
        means = torch.randn(4, 3, generator=gen, dtype=torch.float64, requires_grad=True)
        center = torch.tensor([0.1, -3.0, 0.2], dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda c, m: eval_sh(3, c, view_directions(m, center)), (coeffs, means))
