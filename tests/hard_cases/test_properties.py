"""Property-based tests (hypothesis) over random cameras, Gaussians, rays and colours: outputs
and gradients are always finite, alpha and weights lie in [0, 1], HDR >= 0, LDR in [0, 1]."""

import math

import pytest
import torch
from hard_scenes import backbone_config
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from backbones.gs import render_gaussians
from backbones.nerf import NerfBackbone
from backbones.nerf.rendering import compositing_weights, make_composite, sample_deltas
from backbones.nerf.sampling import ray_segments, sample_pdf, sample_stratified
from mono_hdr_plugin.core.backbone import SceneInfo
from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.core.converters import H2LColorConverter, L2HColorConverter, PerChannelCRF, PlainH2L, PlainL2H
from mono_hdr_plugin.core.metrics import hdr_metrics, mu_law, normalise_hdr, psnr, ssim

PROPERTY = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def floats(low, high):
    return st.floats(low, high, allow_nan=False, allow_infinity=False)


@st.composite
def cameras(draw, max_size: int = 20):
    """Anywhere from inside the unit box to far away, looking at a point near the origin."""
    eye = torch.tensor([draw(floats(-6, 6)) for _ in range(3)])
    target = torch.tensor([draw(floats(-0.5, 0.5)) for _ in range(3)])
    if (eye - target).norm() < 0.05:
        eye = target + torch.tensor([0.0, -0.5, 0.0])
    width, height = draw(st.integers(4, max_size)), draw(st.integers(4, max_size))
    focal = draw(floats(2.0, 60.0))
    near = draw(floats(0.0, 2.0))
    far = near + draw(st.sampled_from([0.0, 1e-6, draw(floats(0.01, 10.0))]))
    return Camera(
        look_at(eye, target),
        fx=focal,
        fy=focal * draw(floats(0.5, 2.0)),
        cx=draw(floats(0, width)),
        cy=draw(floats(0, height)),
        width=width,
        height=height,
        near=near,
        far=far,
    )


@st.composite
def gaussians(draw):
    n = draw(st.integers(0, 12))
    seed = draw(st.integers(0, 2**31 - 1))
    gen = torch.Generator().manual_seed(seed)
    log_scale_range = draw(st.sampled_from([(-6.0, 1.0), (-40.0, -20.0), (3.0, 20.0)]))
    low, high = log_scale_range
    quats = torch.randn(n, 4, generator=gen)
    quats[torch.rand(n, generator=gen) < 0.2] = 0.0  # some zero-norm quaternions
    return {
        "means": (torch.rand(n, 3, generator=gen) * 2 - 1) * draw(floats(0.1, 5.0)),
        "quats": quats,
        "scales": torch.exp(low + (high - low) * torch.rand(n, 3, generator=gen)),
        "opacities": torch.rand(n, generator=gen) ** draw(floats(0.1, 5.0)),
        "values": torch.rand(n, 3, generator=gen) * draw(st.sampled_from([1.0, 1e3, 1e6])),
    }


class TestRasteriserProperties:
    @pytest.mark.parametrize("backend", ["kernel", "torch"])
    @PROPERTY
    @given(camera=cameras(), scene=gaussians())
    def test_finite_outputs_and_gradients_alpha_in_unit_interval(self, backend, camera, scene):
        leaves = {k: v.clone().requires_grad_(True) for k, v in scene.items()}
        image, alpha, projected = render_gaussians(
            leaves["means"],
            leaves["quats"],
            leaves["scales"],
            leaves["opacities"],
            leaves["values"],
            camera,
            backend=backend,
        )
        assert image.shape == (camera.height, camera.width, 3) and alpha.shape == (camera.height, camera.width, 1)
        assert torch.isfinite(image).all() and torch.isfinite(alpha).all()
        assert ((alpha >= 0) & (alpha <= 1)).all()
        assert (image >= 0).all()  # non-negative values composite to a non-negative image
        assert (projected.radii >= 0).all()
        loss = (image * torch.linspace(-1, 1, image.numel()).reshape(image.shape)).sum() + alpha.sum()
        if loss.requires_grad:
            loss.backward()
            for name, leaf in leaves.items():
                assert leaf.grad is None or torch.isfinite(leaf.grad).all(), name


@st.composite
def densities(draw):
    rays, samples = draw(st.integers(1, 6)), draw(st.integers(1, 12))
    scale = draw(st.sampled_from([0.0, 1e-30, 1.0, 1e3, 1e30]))
    gen = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    density = torch.rand(rays, samples, generator=gen) * scale
    density[torch.rand(rays, samples, generator=gen) < 0.3] = 0.0
    t = torch.sort(torch.rand(rays, samples, generator=gen) * draw(floats(0.0, 10.0)), -1).values
    return density, t, t[:, -1] + draw(floats(0.0, 2.0))


class TestVolumeRendererProperties:
    @PROPERTY
    @given(case=densities())
    def test_weights_in_unit_interval_and_finite_gradients(self, case):
        density, t, t_far = case
        density = density.requires_grad_(True)
        weights = compositing_weights(density, sample_deltas(t, t_far))
        assert torch.isfinite(weights).all() and ((weights >= 0) & (weights <= 1)).all()
        assert (weights.sum(-1) <= 1 + 1e-6).all()
        values = torch.rand(*weights.shape, 6, requires_grad=True)
        image = make_composite(weights, (weights.shape[0],), torch.zeros(3))(values)
        (image * torch.randn_like(image)).sum().backward()
        assert torch.isfinite(image).all()
        assert torch.isfinite(density.grad).all() and torch.isfinite(values.grad).all()

    @PROPERTY
    @given(camera=cameras(max_size=8), samples=st.integers(1, 16))
    def test_ray_samples_stay_inside_their_segment(self, camera, samples):
        origins, directions = camera.rays()
        origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
        t_near, t_far = ray_segments(origins, directions, camera.near, camera.far, (-torch.ones(3), torch.ones(3)))
        assert torch.isfinite(t_near).all() and torch.isfinite(t_far).all() and (t_far >= t_near).all()
        t = sample_stratified(t_near, t_far, samples, perturb=True)
        assert ((t >= t_near[:, None] - 1e-5) & (t <= t_far[:, None] + 1e-5)).all()
        edges = sample_stratified(t_near, t_far, samples + 1, perturb=False)
        fine = sample_pdf(edges, torch.rand(t.shape[0], samples) * (torch.rand(1) > 0.5), 8, deterministic=False)
        assert torch.isfinite(fine).all()

    @pytest.mark.parametrize("field", ["cpu", "paper"])
    @PROPERTY
    @given(camera=cameras(max_size=8))
    def test_backbone_render_finite_with_finite_gradients(self, field, camera):
        scene = SceneInfo(bounds_min=-torch.ones(3), bounds_max=torch.ones(3), train_cameras=[camera])
        torch.manual_seed(0)
        backbone = NerfBackbone(backbone_config("nerf", field=field), scene)
        features = backbone.render_ldr_features(camera)
        hdr_colors = torch.nn.functional.softplus(features.raw_colors)
        image = features.composite(torch.cat([features.colors, hdr_colors], -1))
        weights, alpha = features.extras["weights"], features.extras["alpha"]
        assert torch.isfinite(image).all() and ((weights >= 0) & (weights <= 1)).all()
        assert ((alpha >= 0) & (alpha <= 1 + 1e-6)).all()
        assert ((image[..., :3] >= 0) & (image[..., :3] <= 1 + 1e-6)).all() and (image[..., 3:] >= 0).all()
        image.sum().backward()
        for name, parameter in backbone.named_parameters():
            assert parameter.grad is None or torch.isfinite(parameter.grad).all(), name


def colours(low=0.0, high=1.0):
    return st.lists(floats(low, high), min_size=3, max_size=3 * 16).filter(lambda v: len(v) % 3 == 0)


class TestConverterProperties:
    @pytest.mark.parametrize("converter", [L2HColorConverter, PlainL2H])
    @PROPERTY
    @given(values=colours(), seed=st.integers(0, 1000))
    def test_l2h_hdr_non_negative_and_finite(self, converter, values, seed):
        torch.manual_seed(seed)
        ldr = torch.tensor(values).reshape(-1, 3).requires_grad_(True)
        model = converter(hidden=16)
        hdr = model(ldr)
        assert hdr.shape == ldr.shape and torch.isfinite(hdr).all() and (hdr >= 0).all()
        hdr.sum().backward()
        assert torch.isfinite(ldr.grad).all()
        assert all(torch.isfinite(p.grad).all() for p in model.parameters())

    @pytest.mark.parametrize("converter", [H2LColorConverter, PlainH2L, PerChannelCRF])
    @PROPERTY
    @given(values=colours(-1e6, 1e6), seed=st.integers(0, 1000))
    def test_h2l_ldr_in_unit_interval_and_finite(self, converter, values, seed):
        torch.manual_seed(seed)
        hdr = torch.tensor(values).reshape(-1, 3).requires_grad_(True)
        model = converter(hidden=16)
        ldr = model(hdr)
        assert torch.isfinite(ldr).all() and ((ldr >= 0) & (ldr <= 1)).all()
        ldr.sum().backward()
        assert torch.isfinite(hdr.grad).all()
        assert all(torch.isfinite(p.grad).all() for p in model.parameters())


@st.composite
def hdr_images(draw):
    size = draw(st.integers(11, 16))
    gen = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    kind = draw(st.sampled_from(["random", "zero", "constant", "decades", "sparse"]))
    if kind == "zero":
        return torch.zeros(size, size, 3)
    if kind == "constant":
        return torch.full((size, size, 3), draw(floats(1e-30, 1e30)))
    if kind == "decades":
        return 10.0 ** (torch.rand(size, size, 3, generator=gen) * 12 - 6)
    image = torch.rand(size, size, 3, generator=gen) * draw(floats(1e-6, 1e6))
    if kind == "sparse":
        image[torch.rand(size, size, generator=gen) < 0.9] = 0.0
    return image


class TestMetricProperties:
    @PROPERTY
    @given(pred=hdr_images(), gt=hdr_images())
    def test_hdr_normalisation_and_metrics(self, pred, gt):
        size = min(pred.shape[0], gt.shape[0])
        pred, gt = pred[:size, :size].clone().requires_grad_(True), gt[:size, :size]
        normalised = normalise_hdr(pred)
        assert torch.isfinite(normalised).all() and ((normalised >= 0) & (normalised <= 1)).all()
        normalised.sum().backward()
        assert torch.isfinite(pred.grad).all()
        for key, value in hdr_metrics(pred.detach(), gt).items():
            assert not math.isnan(value), key
            assert math.isfinite(value) or (value == math.inf and "psnr" in key), (key, value)

    @PROPERTY
    @given(
        seed=st.integers(0, 2**31 - 1),
        size=st.integers(11, 16),
        same=st.booleans(),
        flat=st.sampled_from([None, 0.0, 1.0]),
    )
    def test_ldr_psnr_ssim(self, seed, size, same, flat):
        gen = torch.Generator().manual_seed(seed)
        gt = torch.rand(size, size, 3, generator=gen) if flat is None else torch.full((size, size, 3), flat)
        pred = (gt.clone() if same else torch.rand(size, size, 3, generator=gen)).requires_grad_(True)
        value = psnr(pred.detach(), gt)
        assert value == math.inf if same else math.isfinite(value)
        score = ssim(pred, gt)
        score.backward()
        assert torch.isfinite(score) and -1 <= score.item() <= 1 + 1e-6
        assert torch.isfinite(pred.grad).all()
        assert ((mu_law(pred.detach()) >= 0) & (mu_law(pred.detach()) <= 1)).all()
