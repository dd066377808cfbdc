"""docs/robustness.md, one named test per numerical hard case, through the public APIs of
the rasteriser (backbones.gs), the volume renderer (backbones.nerf), the converters and the
metrics. Data, checkpoint and CLI cases are in test_bad_input_matrix.py / test_crash_safety.py.
"""

import json
import math

import pytest
import torch
from hard_scenes import backbone_config, make_scene

from backbones.gs import GaussianBackbone, render_gaussians
from backbones.nerf import NerfBackbone
from backbones.nerf.rendering import compositing_weights, make_composite
from backbones.nerf.sampling import ray_segments, sample_pdf
from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.core.metrics import hdr_metrics, normalise_hdr, psnr
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.io import read_exr, write_exr, write_json
from mono_hdr_plugin.methods.base import MethodOutput
from mono_hdr_plugin.training.evaluation import save_view_renders

BACKENDS = ("kernel", "torch")
SIZE = 24


def front_camera(near: float = 0.1) -> Camera:
    """At (0, -4, 0) looking at the origin along +y (world z up)."""
    return Camera(
        look_at(torch.tensor([0.0, -4.0, 0.0]), torch.zeros(3)),
        fx=SIZE,
        fy=SIZE,
        cx=SIZE / 2,
        cy=SIZE / 2,
        width=SIZE,
        height=SIZE,
        near=near,
    )


def one_gaussian(mean=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0), scale=(0.3, 0.3, 0.3), opacity=0.8):
    return {
        "means": torch.tensor([mean], dtype=torch.float32),
        "quats": torch.tensor([quat]),
        "scales": torch.tensor([scale]),
        "opacities": torch.tensor([opacity]),
        "values": torch.tensor([[0.2, 0.5, 0.9]]),
    }


def stack(*gaussians):
    return {k: torch.cat([g[k] for g in gaussians]) for k in gaussians[0]}


def render_with_grads(gaussians: dict, camera: Camera, backend: str):
    """Render, backpropagate a pixel-weighted sum; returns image, alpha, projection, gradients."""
    leaves = {k: v.clone().requires_grad_(True) for k, v in gaussians.items()}
    image, alpha, projected = render_gaussians(
        leaves["means"],
        leaves["quats"],
        leaves["scales"],
        leaves["opacities"],
        leaves["values"],
        camera,
        backend=backend,
    )
    weights = torch.rand(image.shape, generator=torch.Generator().manual_seed(0)) - 0.3
    loss = (image * weights).sum() + alpha.sum()
    if loss.requires_grad:  # the torch twin builds no graph when no pixel is touched
        loss.backward()
    return image, alpha, projected, {k: v.grad for k, v in leaves.items()}


def assert_finite_render(image, alpha, grads):
    assert torch.isfinite(image).all() and torch.isfinite(alpha).all()
    assert ((alpha >= 0) & (alpha <= 1)).all()
    for name, grad in grads.items():
        assert grad is None or torch.isfinite(grad).all(), f"gradient of {name} is not finite"


# ------------------------------------------------------------------ Gaussian rasteriser
@pytest.mark.parametrize("backend", BACKENDS)
def test_gs_point_gaussian_gets_dilation_not_a_singular_covariance(backend):
    """Zero scales give a zero 3D covariance; the 0.3 px^2 dilation keeps the 2D one invertible."""
    image, alpha, projected, grads = render_with_grads(one_gaussian(scale=(0.0, 0.0, 0.0)), front_camera(), backend)
    assert_finite_render(image, alpha, grads)
    assert projected.radii[0] > 0 and torch.isfinite(projected.conics).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_gs_non_finite_footprint_is_culled(backend):
    """Scales of 1e20 overflow the 2D covariance (det inf or <= 0 after rounding): culled, no NaN."""
    image, alpha, projected, grads = render_with_grads(
        stack(one_gaussian(scale=(1e20, 1e20, 1e20)), one_gaussian(mean=(0.2, 0.0, 0.1))), front_camera(), backend
    )
    assert_finite_render(image, alpha, grads)
    assert projected.radii[0] == 0 and projected.radii[1] > 0
    assert (grads["means"][0] == 0).all() and (grads["scales"][0] == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_gs_behind_and_at_near_plane_are_culled_with_zero_gradient(backend):
    camera = front_camera(near=0.5)
    eye, forward = camera.center, camera.c2w[:3, 2]
    rows = [one_gaussian(mean=(eye + d * forward).tolist()) for d in (-1.0, 0.0, 0.3, 0.499)]
    visible = one_gaussian()
    image, alpha, projected, grads = render_with_grads(stack(*rows, visible), camera, backend)
    assert_finite_render(image, alpha, grads)
    assert (projected.radii[:4] == 0).all() and projected.radii[4] > 0
    for name in ("means", "quats", "scales", "opacities", "values"):
        assert (grads[name][:4] == 0).all(), f"a culled Gaussian got a {name} gradient"


@pytest.mark.parametrize("backend", BACKENDS)
def test_gs_huge_screen_radius_is_clipped_to_the_image(backend):
    camera = front_camera(near=0.1)
    huge = one_gaussian(mean=(camera.center + 0.2 * camera.c2w[:3, 2]).tolist(), scale=(30.0, 30.0, 0.01))
    image, alpha, projected, grads = render_with_grads(huge, camera, backend)
    assert_finite_render(image, alpha, grads)
    box = projected.boxes[0]
    assert 0 <= box[0] <= box[2] <= SIZE and 0 <= box[1] <= box[3] <= SIZE


@pytest.mark.parametrize("backend", BACKENDS)
def test_gs_zero_norm_quaternion_renders_as_identity(backend):
    zero = render_with_grads(one_gaussian(quat=(0.0, 0.0, 0.0, 0.0)), front_camera(), backend)
    identity = render_with_grads(one_gaussian(), front_camera(), backend)
    assert_finite_render(zero[0], zero[1], zero[3])
    torch.testing.assert_close(zero[0], identity[0])


@pytest.mark.parametrize("log_scale", [-1000.0, -30.0, 30.0, 1000.0])
def test_gs_backbone_scales_that_underflow_or_overflow_exp(log_scale):
    scene = make_scene()
    model = GaussianBackbone(backbone_config("gs"), scene.scene_info())
    with torch.no_grad():
        model.log_scales[:10] = log_scale
    features = model.render_ldr_features(scene.train[0].camera)
    image = features.composite(torch.cat([features.colors, features.raw_colors.exp()], -1))
    image.sum().backward()
    assert torch.isfinite(image).all()
    for name, parameter in model.named_parameters():
        assert parameter.grad is None or torch.isfinite(parameter.grad).all(), name


@pytest.mark.parametrize("backend", BACKENDS)
def test_gs_alpha_is_clamped_at_0_99(backend):
    image, alpha, _, grads = render_with_grads(
        one_gaussian(opacity=1.0, scale=(1.0, 1.0, 1.0)), front_camera(), backend
    )
    assert_finite_render(image, alpha, grads)
    assert float(alpha.detach().max()) == pytest.approx(0.99, abs=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gs_alpha_below_1_over_255_is_skipped(backend):
    image, alpha, projected, grads = render_with_grads(one_gaussian(opacity=1.0 / 300), front_camera(), backend)
    assert_finite_render(image, alpha, grads)
    assert alpha.max() == 0 and image.abs().max() == 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_gs_compositing_stops_when_transmittance_falls_below_1e_4(backend):
    """Ten opaque Gaussians in a row: blending stops before T < 1e-4; the ones behind get no gradient."""
    layers = stack(*[one_gaussian(mean=(0.0, 0.2 * k, 0.0), opacity=1.0, scale=(1.0, 1.0, 1.0)) for k in range(10)])
    image, alpha, _, grads = render_with_grads(layers, front_camera(), backend)
    assert_finite_render(image, alpha, grads)
    assert float(alpha.detach().max()) <= 1 - 1e-4 + 1e-6
    values = layers["values"].clone().requires_grad_(True)
    centre, _, _ = render_gaussians(
        layers["means"], layers["quats"], layers["scales"], layers["opacities"], values, front_camera(), backend=backend
    )
    centre[SIZE // 2, SIZE // 2].sum().backward()
    # alpha 0.99 each: the second layer would take T from 0.01 to 0.01 * 0.01, not above 1e-4 in
    # float32, so the first layer ends the pixel and the nine behind it get no gradient
    assert (values.grad[:1] != 0).all() and (values.grad[1:] == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_gs_no_gaussians_at_all(backend):
    empty = {
        "means": torch.zeros(0, 3),
        "quats": torch.zeros(0, 4),
        "scales": torch.zeros(0, 3),
        "opacities": torch.zeros(0),
        "values": torch.zeros(0, 3),
    }
    image, alpha, _, grads = render_with_grads(empty, front_camera(), backend)
    assert_finite_render(image, alpha, grads)
    assert image.abs().max() == 0 and alpha.max() == 0


# ------------------------------------------------------------------- volume renderer
def nerf_backbone(field: str, activation: str = "softplus") -> NerfBackbone:
    config = backbone_config("nerf", field=field)
    config.field.density_activation = activation
    scene = make_scene()
    return NerfBackbone(config, scene.scene_info())


def render_nerf_with_grads(backbone: NerfBackbone, camera: Camera):
    features = backbone.render_ldr_features(camera)
    image = features.composite(torch.cat([features.colors, features.raw_colors], -1))
    loss = image.square().sum() + sum(aux.composite(aux.colors).sum() for aux in features.auxiliary)
    if loss.requires_grad:
        loss.backward()
    weights = features.extras["weights"]
    assert torch.isfinite(image).all() and torch.isfinite(weights).all()
    assert ((weights >= 0) & (weights <= 1)).all() and (weights.sum(-1) <= 1 + 1e-5).all()
    # sigmoid colours stay in [0, 1]; the grid field's softplus colours are only >= 0
    upper = math.inf if backbone.uses_grid and backbone.config.field.color_activation == "softplus" else 1.0
    assert ((features.colors >= 0) & (features.colors <= upper)).all()
    for name, parameter in backbone.named_parameters():
        assert parameter.grad is None or torch.isfinite(parameter.grad).all(), name
    return image, features


FIELDS = [("paper", "relu"), ("paper", "softplus"), ("cpu", "relu"), ("cpu", "softplus")]


@pytest.mark.parametrize("field,activation", FIELDS)
def test_nerf_empty_rays_that_miss_the_box(field, activation):
    away = Camera(
        look_at(torch.tensor([0.0, -4.0, 0.0]), torch.tensor([0.0, -8.0, 0.0])),
        fx=8,
        fy=8,
        cx=4,
        cy=4,
        width=8,
        height=8,
        near=0.1,
        far=6.0,
    )
    image, features = render_nerf_with_grads(nerf_backbone(field, activation), away)
    assert image.abs().max() == 0 and features.extras["alpha"].max() == 0


@pytest.mark.parametrize("field,activation", FIELDS)
def test_nerf_far_equals_near(field, activation):
    camera = Camera(
        look_at(torch.tensor([0.0, -3.0, 0.0]), torch.zeros(3)),
        fx=8,
        fy=8,
        cx=4,
        cy=4,
        width=8,
        height=8,
        near=2.5,
        far=2.5,
    )
    image, features = render_nerf_with_grads(nerf_backbone(field, activation), camera)
    assert features.extras["alpha"].max() == 0


@pytest.mark.parametrize("field,activation", FIELDS)
@pytest.mark.parametrize(
    "eye", [(3.0, 0.0, 0.0), (3.0, 1.0, 0.0), (3.0, 1.0, 1.0)], ids=["through-centre", "along-face", "along-edge"]
)
def test_nerf_rays_parallel_to_a_bounding_plane(field, activation, eye):
    """Odd-sized image: the central ray is exactly axis-aligned (direction components 0)."""
    eye = torch.tensor(eye)
    camera = Camera(
        look_at(eye, eye - torch.tensor([1.0, 0.0, 0.0])),
        fx=7,
        fy=7,
        cx=3.5,
        cy=3.5,
        width=7,
        height=7,
        near=0.1,
        far=6.0,
    )
    _, directions = camera.rays()
    assert (directions[3, 3, 1:] == 0).all()
    render_nerf_with_grads(nerf_backbone(field, activation), camera)


def test_nerf_all_zero_weights_give_a_uniform_pdf_not_nan():
    edges = torch.linspace(0, 1, 9).expand(4, 9).contiguous()
    samples = sample_pdf(edges, torch.zeros(4, 8), 16, deterministic=True)
    assert torch.isfinite(samples).all() and (samples >= 0).all() and (samples <= 1).all()
    densities = torch.zeros(4, 8, requires_grad=True)
    weights = compositing_weights(densities, torch.full((4, 8), 0.1))
    composite = make_composite(weights, (4,), torch.zeros(3))
    values = torch.rand(4, 8, 3, requires_grad=True)
    composite(values).sum().backward()
    assert (weights == 0).all() and torch.isfinite(densities.grad).all() and (values.grad == 0).all()


def test_nerf_opaque_and_huge_densities_keep_weights_in_unit_interval():
    densities = torch.tensor([[0.0, 1e30, 1e30, 5.0], [1e-30, 1e-30, 1e38, 0.0]], requires_grad=True)
    weights = compositing_weights(densities, torch.tensor([[0.1, 0.1, 0.0, 1e6], [1.0, 1.0, 1.0, 1.0]]))
    weights.sum().backward()
    assert torch.isfinite(weights).all() and ((weights >= 0) & (weights <= 1)).all()
    assert (weights.sum(-1) <= 1).all() and torch.isfinite(densities.grad).all()


def test_nerf_ray_segments_on_degenerate_rays_stay_ordered_and_finite():
    origins = torch.tensor([[0.0, -3.0, 0.0], [0.0, -3.0, 5.0], [0.0, 0.0, 0.0], [1.0, -3.0, 1.0]])
    directions = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    t_near, t_far = ray_segments(origins, directions, 0.1, 10.0, (-torch.ones(3), torch.ones(3)))
    assert torch.isfinite(t_near).all() and torch.isfinite(t_far).all() and (t_far >= t_near).all()
    assert t_far[1] == t_near[1]  # misses the box: zero-length segment


# ---------------------------------------------------------------------- HDR values
def test_hdr_render_above_float16_max_is_written_as_float32_exr(tmp_path):
    """A render above 65504 is saved exactly (float32 EXR); half EXR refuses instead of writing inf."""
    hdr = torch.logspace(0, 6, 16 * 16 * 3).reshape(16, 16, 3)
    camera = make_scene().test[0].camera
    view = make_scene().test[0]
    save_view_renders(tmp_path, view, MethodOutput(ldr=torch.rand(16, 16, 3), hdr=hdr))
    back = read_exr(tmp_path / f"{view.name}_hdr.exr")
    assert camera.width == 16 and back.max() > 65504
    torch.testing.assert_close(torch.from_numpy(back), hdr)
    with pytest.raises(DatasetError, match="half.exr.*65504"):
        write_exr(tmp_path / "half.exr", hdr.numpy(), half=True)


def test_normalise_hdr_of_float16_images():
    """float16 cannot hold the 1e-12 floor of the max: an all-zero half image must not give 0/0."""
    zero = normalise_hdr(torch.zeros(8, 8, 3, dtype=torch.float16))
    assert torch.isfinite(zero).all() and (zero == 0).all()
    bright = torch.full((8, 8, 3), 60000.0, dtype=torch.float16)
    assert torch.isfinite(normalise_hdr(bright)).all()
    assert torch.isfinite(normalise_hdr(torch.full((8, 8, 3), 1e-7).half())).all()


@pytest.mark.parametrize("value", [0.0, 1e-30, 0.7, 1e6, 3e38])
def test_normalise_constant_image(value):
    image = torch.full((12, 12, 3), value, requires_grad=True)
    normalised = normalise_hdr(image)
    normalised.sum().backward()
    assert torch.isfinite(normalised).all() and ((normalised >= 0) & (normalised <= 1)).all()
    assert torch.isfinite(image.grad).all()


def test_hdr_metrics_of_constant_and_zero_images_are_never_nan():
    for gt in (torch.zeros(16, 16, 3), torch.full((16, 16, 3), 0.7)):
        for pred in (torch.zeros(16, 16, 3), torch.full((16, 16, 3), 3.0), torch.rand(16, 16, 3)):
            for key, value in hdr_metrics(pred, gt).items():
                assert not math.isnan(value), (key, gt[0, 0, 0].item(), pred[0, 0, 0].item())


def test_psnr_of_identical_images_is_inf_and_survives_metrics_json(tmp_path):
    image = torch.rand(16, 16, 3)
    assert psnr(image, image.clone()) == math.inf
    write_json(tmp_path / "metrics.json", {"ldr_psnr": psnr(image, image.clone())})
    assert json.loads((tmp_path / "metrics.json").read_text())["ldr_psnr"] == math.inf
