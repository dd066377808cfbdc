"""The rasteriser's Python side: what it accepts, what each backend runs, and gradients that reach
the kernel in layouts torch likes to hand out (expanded, strided, other dtypes)."""

import pytest
import torch
from gs_scenes import make_camera, random_gaussians

from backbones.gs import rasterizer, reference
from backbones.gs.rasterizer import project_gaussians, render_gaussians
from mono_hdr_plugin.core.cameras import Camera

PARAMS = ("means", "quats", "scales", "opacities", "values")


def leaves(scene: dict) -> dict:
    return {k: scene[k].clone().requires_grad_() for k in PARAMS}


def gradients_of(loss_of, scene: dict, camera, backend: str) -> dict:
    inputs = leaves(scene)
    loss_of(render_gaussians(*(inputs[k] for k in PARAMS), camera, backend=backend)).backward()
    return {k: v.grad for k, v in inputs.items()}


def assert_same_gradients(got: dict, want: dict) -> None:
    for name, expected in want.items():
        if expected is None:  # alpha does not depend on the values
            assert got[name] is None or not got[name].any(), name
            continue
        scale = float(expected.abs().max().clamp_min(1e-9))
        torch.testing.assert_close(got[name], expected, rtol=1e-4, atol=1e-4 * scale, msg=name)


class TestPlainSums:
    """`image.sum()` hands the backward pass an expanded gradient (stride 0): the kernel must not
    read it as if it were laid out in memory."""

    @pytest.mark.parametrize("loss", ["image", "alpha", "both"])
    def test_kernel_matches_twin(self, loss):
        camera = make_camera()
        scene = random_gaussians(120, seed=3)
        loss_of = {
            "image": lambda out: out[0].sum(),
            "alpha": lambda out: out[1].sum(),
            "both": lambda out: out[0].sum() + 2 * out[1].sum(),
        }[loss]
        assert_same_gradients(
            gradients_of(loss_of, scene, camera, "kernel"), gradients_of(loss_of, scene, camera, "torch")
        )

    def test_projection_sums(self):
        camera = make_camera()
        scene = random_gaussians(120, seed=4)
        grads = {}
        for backend in ("kernel", "torch"):
            inputs = leaves(scene)
            projected = project_gaussians(
                inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"], camera, backend=backend
            )
            (projected.means2d.sum() + projected.conics.sum() + projected.depths.sum()).backward()
            grads[backend] = {k: inputs[k].grad for k in ("means", "quats", "scales")}
        assert_same_gradients(grads["kernel"], grads["torch"])


class TestInputs:
    @pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
    def test_strided_and_double_inputs_render_as_contiguous_float(self, dtype):
        camera = make_camera()
        scene = random_gaussians(80, seed=5)
        wide = {k: torch.stack([v, torch.zeros_like(v)], 1).to(dtype) for k, v in scene.items()}
        strided = {k: v[:, 0] for k, v in wide.items()}  # every other row in memory (a float32 one stays strided)
        assert not strided["means"].is_contiguous() and strided["means"].dtype == dtype
        double_camera = Camera(
            camera.c2w.double(), camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, camera.near
        )
        image, alpha, _ = render_gaussians(*(strided[k] for k in PARAMS), double_camera)
        expected_image, expected_alpha, _ = render_gaussians(*(scene[k] for k in PARAMS), camera)
        assert image.dtype == torch.float32
        torch.testing.assert_close(image, expected_image)
        torch.testing.assert_close(alpha, expected_alpha)

    def test_alpha_has_one_channel(self):
        camera = make_camera(width=24, height=20)
        scene = random_gaussians(50, seed=6, channels=5)
        image, alpha, _ = render_gaussians(*(scene[k] for k in PARAMS), camera)
        assert image.shape == (20, 24, 5) and alpha.shape == (20, 24, 1)
        assert 0.2 < alpha.max() <= 1.0 and alpha.min() >= 0.0

    @pytest.mark.parametrize(
        "name,bad",
        [
            ("means", torch.zeros(5, 2)),
            ("means", torch.zeros(5, 3, 1)),
            ("quats", torch.zeros(5, 3)),
            ("scales", torch.zeros(5, 4)),
            ("quats", torch.zeros(4, 4)),
            ("scales", torch.zeros(6, 3)),
            ("opacities", torch.zeros(5, 1)),
        ],
    )
    def test_bad_shapes_are_refused_with_the_name(self, name, bad):
        scene = random_gaussians(5)
        scene[name] = bad
        with pytest.raises(ValueError, match=name if bad.shape[0] == 5 and name != "opacities" else "share N"):
            project_gaussians(*(scene[k] for k in PARAMS[:4]), make_camera())


class TestBackends:
    def test_torch_backend_never_touches_the_extension(self, monkeypatch):
        def unavailable():
            raise RuntimeError("the C++ extension must not be used by the torch backend")

        monkeypatch.setattr(rasterizer, "load_extension", unavailable)
        scene = random_gaussians(30, seed=7)
        image, alpha, projected = render_gaussians(*(scene[k] for k in PARAMS), make_camera(), backend="torch")
        assert projected.backend == "torch" and alpha.max() > 0

    def test_kernel_backend_never_runs_the_twin(self, monkeypatch):
        def twin(*args, **kwargs):
            raise RuntimeError("the kernel backend must not run the torch twin")

        for name in ("project_gaussians_torch", "bin_tiles_torch", "rasterize_tiles_torch"):
            monkeypatch.setattr(reference, name, twin)
        scene = random_gaussians(30, seed=7)
        image, alpha, projected = render_gaussians(*(scene[k] for k in PARAMS), make_camera(), backend="kernel")
        assert projected.backend == "kernel" and alpha.max() > 0
