"""Training scenarios that push the numbers to their limits (issue 8): each trains a few hundred
steps and must end with finite parameters, losses and metrics, never NaN.

Each case runs on one backbone in the default suite and on every backbone it applies to under
`-m slow` (more steps). Scenes are synthetic (hard_scenes.py): 16 px, seconds per run.
"""

import math

import pytest
import torch
from hard_scenes import BACKBONES, EXPOSURES, make_scene, make_trainer, orbit_camera, photograph, train_and_check

from backbones.gs import GaussianBackbone
from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.data.io import read_exr

STEPS = 200
SLOW_STEPS = 400


def on(default: str, applicable=BACKBONES):
    """Parametrise over backbones: `default` in the default suite, the others marked slow."""
    return pytest.mark.parametrize(
        "backbone,steps",
        [
            pytest.param(
                name,
                STEPS if name == default else SLOW_STEPS,
                id=name,
                marks=() if name == default else pytest.mark.slow,
            )
            for name in applicable
        ],
    )


def saturated_fraction(scene) -> float:
    return float(torch.cat([(v.image >= 1.0).flatten() for v in scene.train]).float().mean())


def black_fraction(scene) -> float:
    return float(torch.cat([(v.image <= 0.0).flatten() for v in scene.train]).float().mean())


@on("gs")
def test_mostly_saturated_views_t5_only(tmp_path, backbone, steps):
    scene = make_scene(exposure=EXPOSURES[4])
    assert saturated_fraction(scene) > 0.9
    train_and_check(make_trainer(tmp_path, backbone, scene, steps), steps)


@on("nerf")
def test_mostly_black_views_t1_only(tmp_path, backbone, steps):
    scene = make_scene(exposure=EXPOSURES[0], hdr_transform=lambda hdr, i: hdr * 1e-5)
    assert black_fraction(scene) > 0.8
    train_and_check(make_trainer(tmp_path, backbone, scene, steps), steps)


def twelve_decades(hdr, index):
    """Map the pattern onto 1e-6 .. 1e6, log-uniformly."""
    unit = (hdr - hdr.min()) / (hdr.max() - hdr.min())
    return 10.0 ** (12.0 * unit - 6.0)


@on("voxel-grid")
def test_hdr_values_from_1e_minus_6_to_1e6(tmp_path, backbone, steps):
    scene = make_scene(exposure=1.0, hdr_transform=twelve_decades)
    hdr = torch.stack([v.hdr for v in scene.train])
    assert hdr.min() == pytest.approx(1e-6, rel=1e-3) and hdr.max() == pytest.approx(1e6, rel=1e-3)
    train_and_check(make_trainer(tmp_path, backbone, scene, steps), steps)


@on("gs")
def test_hdr_above_float16_max_trains_and_renders_exr(tmp_path, backbone, steps):
    """Ground truth up to 2e5 (float16 holds 65504): training and the EXR renders stay finite."""
    scene = make_scene(exposure=1e-5, hdr_transform=lambda hdr, i: hdr * 5e4)
    assert max(float(v.hdr.max()) for v in scene.train) > 65504
    assert torch.isinf(scene.train[0].hdr.half()).any()  # the case is real: half precision overflows
    trainer = make_trainer(tmp_path, backbone, scene, steps, save_renders=True)
    train_and_check(trainer, steps)
    renders = sorted((tmp_path / "run" / "renders").glob("*_hdr.exr"))
    assert len(renders) == len(scene.test)
    for path in renders:
        assert torch.isfinite(torch.from_numpy(read_exr(path))).all(), path


@on("nerf")
def test_single_training_view(tmp_path, backbone, steps):
    scene = make_scene(train_views=1, test_views=2)
    assert len(scene.train) == 1
    train_and_check(make_trainer(tmp_path, backbone, scene, steps), steps)


def inside_camera(index: int, count: int, size: int) -> Camera:
    """Cameras inside the scene box [-1, 1]^3, looking through the origin, near plane close."""
    angle = 2 * math.pi * index / count
    eye = torch.tensor([0.5 * math.cos(angle), 0.5 * math.sin(angle), 0.2])
    return Camera(
        look_at(eye, torch.zeros(3)),
        fx=1.1 * size,
        fy=1.1 * size,
        cx=size / 2,
        cy=size / 2,
        width=size,
        height=size,
        near=0.05,
        far=4.0,
    )


@on("nerf", applicable=("nerf", "voxel-grid"))
def test_camera_inside_the_scene_bounds(tmp_path, backbone, steps):
    scene = make_scene(camera_for=inside_camera)
    centre = scene.train[0].camera.center
    assert (centre > scene.bounds_min).all() and (centre < scene.bounds_max).all()
    train_and_check(make_trainer(tmp_path, backbone, scene, steps), steps)


@on("gs", applicable=("gs",))
def test_camera_inside_a_gaussian(tmp_path, backbone, steps):
    scene = make_scene()
    trainer = make_trainer(tmp_path, backbone, scene, steps)
    model: GaussianBackbone = trainer.backbone
    camera = scene.train[0].camera
    eye, forward = camera.center, camera.c2w[:3, 2]
    with torch.no_grad():
        # at the eye, just behind the near plane, and just in front of it with the eye inside
        for row, distance in enumerate((0.0, 0.5 * camera.near, 1.05 * camera.near)):
            model.means[row] = eye + distance * forward
            model.log_scales[row] = math.log(0.6)
            model.opacity_logits[row] = 4.0
    inside = (model.means[:3] - eye).norm(dim=-1) < 3 * model.log_scales[:3, 0].exp()
    assert inside.all()
    train_and_check(trainer, steps)


@on("gs", applicable=("gs",))
def test_all_gaussians_pruned(tmp_path, backbone, steps):
    """Every Gaussian below the prune threshold: density control keeps one, training goes on."""
    scene = make_scene()
    trainer = make_trainer(tmp_path, backbone, scene, steps)
    with torch.no_grad():
        trainer.backbone.opacity_logits.fill_(-12.0)  # sigmoid = 6e-6 < prune_opacity 0.005
    assert (torch.sigmoid(trainer.backbone.opacity_logits) < trainer.backbone.config.strategy.prune_opacity).all()
    train_and_check(trainer, steps)
    assert trainer.backbone.num_gaussians >= 1


@on("voxel-grid")
def test_constant_hdr_ground_truth(tmp_path, backbone, steps):
    """Constant HDR ground truth carries no HDR information: warned about, left out, never scored."""
    with pytest.warns(UserWarning, match=r"6 view\(s\) carries no HDR information.*one value \(0.7, 0.7, 0.7\)"):
        scene = make_scene(exposure=0.5, hdr_transform=lambda hdr, i: torch.full_like(hdr, 0.7))
    assert all(v.hdr is None for v in scene.train + scene.test)
    metrics = train_and_check(make_trainer(tmp_path, backbone, scene, steps), steps)
    assert metrics["hdr_psnr"] is None


@on("gs")
def test_all_zero_hdr_ground_truth(tmp_path, backbone, steps):
    """All-zero HDR ground truth (and black photos): warned about, left out, trains finite on LDR alone."""
    with pytest.warns(UserWarning, match=r"6 view\(s\) carries no HDR information.*is all zero"):
        scene = make_scene(hdr_transform=lambda hdr, i: torch.zeros_like(hdr))
    assert all(v.hdr is None and not v.image.any() for v in scene.train)
    metrics = train_and_check(make_trainer(tmp_path, backbone, scene, steps), steps)
    assert metrics["hdr_psnr"] is None


@on("voxel-grid")
def test_pure_white_ldr_image(tmp_path, backbone, steps):
    scene = make_scene(ldr_override=lambda i: torch.ones(16, 16, 3))
    assert all((v.image == 1.0).all() for v in scene.train)
    train_and_check(make_trainer(tmp_path, backbone, scene, steps), steps)


@pytest.mark.parametrize(
    "method",
    ["hdr-nerf", pytest.param("hdr-gs", marks=pytest.mark.slow), pytest.param("no-h2l", marks=pytest.mark.slow)],
)
@on("voxel-grid")
def test_baselines_on_twelve_decades(tmp_path, backbone, steps, method):
    """The CRF baselines exponentiate log radiance: the widest HDR range must not overflow them."""
    scene = make_scene(exposure=1.0, hdr_transform=twelve_decades)
    train_and_check(make_trainer(tmp_path, backbone, scene, steps, method=method), steps)


def test_photograph_helper_quantises_and_clips():
    hdr = torch.tensor([[[0.0, 1.0, 1e6]]])
    assert photograph(hdr, 1.0).tolist() == [[[0.0, 1.0, 1.0]]]
    assert orbit_camera(0, 4, 16).width == 16
