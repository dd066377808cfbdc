"""The 3DGS backbone with an environment map behind its splats (--backbone.background)."""

import dataclasses
import math

import numpy as np
import pytest
import torch
from gs_scenes import make_camera
from helpers import quiet_config

from backbones.gs import DefaultStrategy, GaussianBackbone, GaussianConfig, McmcStrategy
from backbones.gs.rasterizer import project_gaussians, rasterize, render_gaussians
from mono_hdr_plugin.core.backbone import LdrFeatures, SceneInfo
from mono_hdr_plugin.core.cameras import look_at
from mono_hdr_plugin.core.environment import EnvironmentMap
from mono_hdr_plugin.core.validation import FlagError, check_flags
from mono_hdr_plugin.data.io import read_exr


def make_scene(points: int | None = 200, unbounded: bool = True, seed: int = 0) -> SceneInfo:
    gen = torch.Generator().manual_seed(seed)
    base = make_camera()
    cameras = [
        dataclasses.replace(base, c2w=look_at(torch.tensor(eye), torch.zeros(3)))
        for eye in ([0.3, -4.0, 0.5], [3.0, -3.0, 0.4], [-3.0, -3.0, 0.6])
    ]
    scene = SceneInfo(bounds_min=-torch.ones(3), bounds_max=torch.ones(3), train_cameras=cameras, unbounded=unbounded)
    if points:
        scene.points = torch.rand(points, 3, generator=gen) * 1.6 - 0.8
        scene.point_colors = (torch.rand(points, 3, generator=gen) * 255).to(torch.uint8)
    return scene


def randomise_environment(environment: EnvironmentMap, seed: int = 1) -> None:
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for texture in environment.textures:
            texture.copy_(torch.rand(texture.shape, generator=gen) - 0.5)


def hand_directions(camera) -> torch.Tensor:
    """Unit world directions through the pixel centres (x + 0.5, y + 0.5), [H, W, 3]."""
    ys, xs = torch.meshgrid(torch.arange(camera.height) + 0.5, torch.arange(camera.width) + 0.5, indexing="ij")
    local = torch.stack([(xs - camera.cx) / camera.fx, (ys - camera.cy) / camera.fy, torch.ones_like(xs)], -1)
    world = local @ camera.c2w[:3, :3].T
    return world / world.norm(dim=-1, keepdim=True)


class TestBackgroundChoice:
    def test_auto_follows_the_scene(self):
        assert GaussianBackbone(GaussianConfig(), make_scene(unbounded=True)).environment is not None
        assert GaussianBackbone(GaussianConfig(), make_scene(unbounded=False)).environment is None
        forced = GaussianBackbone(GaussianConfig(background="environment"), make_scene(unbounded=False))
        assert forced.environment is not None
        assert GaussianBackbone(GaussianConfig(background="none"), make_scene(unbounded=True)).environment is None

    def test_flag_rules(self):
        with pytest.raises(FlagError, match="--background"):
            check_flags(GaussianConfig(background="sky"))
        with pytest.raises(FlagError, match="--lr-environment"):
            check_flags(GaussianConfig(lr_environment=0.0))

    def test_sky_pole_is_the_cameras_up(self):
        backbone = GaussianBackbone(GaussianConfig(), make_scene())
        # the test cameras look at the origin from slightly above: their up is close to world z
        assert float(backbone.environment.frame[2] @ torch.tensor([0.0, 0.0, 1.0])) > 0.99

    def test_starts_at_mid_grey(self):
        scene = make_scene(points=None)
        backbone = GaussianBackbone(GaussianConfig(), scene)
        features = backbone.render_ldr_features(scene.train_cameras[0])
        visible = features.extras["projected"].index.numel()
        torch.testing.assert_close(features.colors[visible:], torch.full_like(features.colors[visible:], 0.5))


class TestComposite:
    """(a) composite = splats + (1 - alpha) * env, against the torch twin and hand-made rays."""

    def test_forward_and_gradients_match_the_hand_composite(self):
        scene = make_scene(points=60)
        camera = scene.train_cameras[0]
        backbone = GaussianBackbone(GaussianConfig(background="environment"), scene)
        randomise_environment(backbone.environment)
        features = backbone.render_ldr_features(camera)
        image = features.composite(torch.cat([features.colors, 2 * features.raw_colors], -1))
        weights = torch.rand(image.shape, generator=torch.Generator().manual_seed(5)) - 0.3
        (image * weights).sum().backward()
        got = [backbone.environment.textures[0].grad.clone(), backbone.opacity_logits.grad.clone()]
        assert torch.equal(features.extras["alpha"], features.extras["alpha"].clamp(0, 1))
        backbone.zero_grad()

        visible = features.extras["projected"].index
        gauss_raw = features.raw_colors[: visible.numel()].detach()
        values = torch.zeros(backbone.num_gaussians, 6)
        values[visible] = torch.cat([(gauss_raw + 0.5).clamp_min(0), 2 * gauss_raw], -1)
        splats, alpha, _ = render_gaussians(
            backbone.means,
            backbone.quats,
            torch.exp(backbone.log_scales),
            torch.sigmoid(backbone.opacity_logits),
            values,
            camera,
            backend="torch",
        )
        env_raw = backbone.environment(hand_directions(camera))
        expected = splats + (1 - alpha) * torch.cat([(env_raw + 0.5).clamp_min(0), 2 * env_raw], -1)
        assert 0.05 < float(alpha.detach().mean()) < 0.95, "the test needs pixels both covered and open"
        torch.testing.assert_close(image.detach(), expected.detach(), rtol=1e-4, atol=1e-5)
        (expected * weights).sum().backward()
        torch.testing.assert_close(got[0], backbone.environment.textures[0].grad, rtol=1e-3, atol=1e-5)
        torch.testing.assert_close(got[1], backbone.opacity_logits.grad, rtol=1e-3, atol=1e-4)

    def test_alpha_stays_the_gaussians_coverage(self):
        scene = make_scene(points=60)
        camera = scene.train_cameras[0]
        with_sky = GaussianBackbone(GaussianConfig(background="environment"), scene)
        features = with_sky.render_ldr_features(camera)
        features.composite(features.colors)
        projected = features.extras["projected"]
        _, alpha = rasterize(projected, features.colors[: projected.index.numel()])
        torch.testing.assert_close(features.extras["alpha"], alpha)


class TestFarPoint:
    """(b) a bright texel at infinity lands where its direction projects, from any camera position."""

    @pytest.mark.parametrize("eye", [(0.3, -4.0, 0.5), (40.0, 25.0, -7.0)])
    def test_bright_texel_at_its_projection(self, eye):
        scene = make_scene(points=None)
        backbone = GaussianBackbone(GaussianConfig(background="environment"), scene)
        with torch.no_grad():
            backbone.opacity_logits.fill_(-30.0)  # no Gaussian in the way
        finest = backbone.environment.textures[0]
        rows, cols = finest.shape[1:]
        row, col = 100, 150
        with torch.no_grad():
            finest[:, row, col] = 50.0
        azimuth = ((col + 0.5) / cols * 2 - 1) * math.pi
        elevation = -((row + 0.5) / rows * 2 - 1) * math.pi / 2
        local = torch.tensor(
            [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
        )
        direction = local @ backbone.environment.frame  # the map's axes are the frame's rows
        eye = torch.tensor(eye)
        c2w = look_at(eye, eye + direction + torch.tensor([0.12, -0.05, 0.08]))  # off the image centre
        camera = dataclasses.replace(make_camera(width=64, height=48), c2w=c2w)
        in_camera = camera.c2w[:3, :3].T @ direction
        assert in_camera[2] > 0, "the texel must lie in front of the camera"
        x = camera.fx * in_camera[0] / in_camera[2] + camera.cx
        y = camera.fy * in_camera[1] / in_camera[2] + camera.cy
        features = backbone.render_ldr_features(camera)
        image = features.composite(features.colors).detach()
        brightest = int(image.sum(-1).argmax())
        found_y, found_x = divmod(brightest, camera.width)
        assert float(image.sum(-1).max()) > 3.0, "the texel's brightness reaches the render"
        assert abs(found_x + 0.5 - float(x)) <= 1.0 and abs(found_y + 0.5 - float(y)) <= 1.0


def descend(backbone: GaussianBackbone, camera, target: torch.Tensor, optimizer) -> LdrFeatures:
    """One optimiser step on the L1 error of the composited render against `target`; the features
    that after_step reads."""
    features = backbone.render_ldr_features(camera)
    loss = (features.composite(features.colors) - target).abs().mean()
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    return features


def adam_state(optimizer, parameters) -> list[dict]:
    return [{k: v.clone() for k, v in optimizer.state[p].items()} for p in parameters]


class TestDensityControlLeavesTheSkyAlone:
    """(c) refinement, pruning and opacity reset edit Gaussians only."""

    @pytest.mark.parametrize(
        "strategy",
        [
            DefaultStrategy(
                refine_start=0, refine_every=1, min_refine_every=1, grad_threshold=0.0, reset_opacity_every=2
            ),
            McmcStrategy(refine_start=0, refine_every=1, min_refine_every=1, grow_fraction=0.5, min_opacity=0.3),
        ],
        ids=["default", "mcmc"],
    )
    def test_environment_and_its_adam_state_unchanged(self, strategy):
        scene = make_scene(points=80)
        camera = scene.train_cameras[0]
        backbone = GaussianBackbone(GaussianConfig(background="environment", strategy=strategy), scene)
        backbone.set_run_length(30_000)  # unscaled schedule: refine every step, reset at step 2
        optimizer = torch.optim.Adam(backbone.parameter_groups(), eps=1e-15)
        target = torch.rand(camera.height, camera.width, 3, generator=torch.Generator().manual_seed(2))
        counts = []
        for step in range(1, 4):
            features = descend(backbone, camera, target, optimizer)
            textures = list(backbone.environment.parameters())
            values, moments = [t.detach().clone() for t in textures], adam_state(optimizer, textures)
            before = backbone.num_gaussians
            backbone.after_step(step, features, optimizer)
            counts.append((before, backbone.num_gaussians))
            group = next(g for g in optimizer.param_groups if g["name"] == "environment")
            assert all(a is b for a, b in zip(group["params"], backbone.environment.parameters()))
            for texture, value, moment in zip(backbone.environment.parameters(), values, moments):
                assert torch.equal(texture, value)
                assert all(torch.equal(optimizer.state[texture][k], v) for k, v in moment.items())
        assert any(a != b for a, b in counts), "density control ran and changed the Gaussians"

    def test_budget_counts_gaussians_only(self):
        scene = make_scene(points=80)
        with_sky = GaussianBackbone(GaussianConfig(background="environment"), scene)
        without = GaussianBackbone(GaussianConfig(background="none"), scene)
        assert with_sky.budget == without.budget and with_sky.num_gaussians == without.num_gaussians == 80


class TestSaving:
    def test_checkpoint_round_trip(self):
        """(d) the map reaches state_dict and a fresh backbone (other Gaussian count) renders the same."""
        scene = make_scene(points=80)
        camera = scene.train_cameras[1]
        trained = GaussianBackbone(GaussianConfig(background="environment"), scene)
        randomise_environment(trained.environment)
        assert any(key.startswith("environment.textures.") for key in trained.state_dict())
        fresh = GaussianBackbone(GaussianConfig(background="environment"), make_scene(points=30, seed=4))
        fresh.load_state_dict(trained.state_dict())
        expected = trained.render_ldr_features(camera)
        got = fresh.render_ldr_features(camera)
        torch.testing.assert_close(got.composite(got.colors), expected.composite(expected.colors))

    def test_export_writes_the_map_beside_the_ply(self, tmp_path):
        backbone = GaussianBackbone(GaussianConfig(background="environment"), make_scene(points=40))
        randomise_environment(backbone.environment)
        ply = backbone.export_ply(tmp_path / "model.ply")
        image = read_exr(tmp_path / "model.environment.exr")
        assert ply.exists() and image.shape == (256, 512, 3)
        # row r, column c of the file is the map's value at that texel centre's direction
        r, c = 77, 301
        azimuth, elevation = ((c + 0.5) / 512 * 2 - 1) * math.pi, -((r + 0.5) / 256 * 2 - 1) * math.pi / 2
        local = torch.tensor(
            [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
        )
        with torch.no_grad():
            expected = backbone.environment(local @ backbone.environment.frame).numpy()
        np.testing.assert_allclose(image[r, c], expected, rtol=1e-5, atol=1e-5)


class TestBoundedScenesUnchanged:
    @pytest.mark.parametrize("background", ["auto", "none"])
    def test_render_is_the_plain_rasterisation(self, background):
        """(e) no environment: the rows are the visible Gaussians and the image is their rasterisation."""
        scene = make_scene(points=80, unbounded=False)
        camera = scene.train_cameras[0]
        backbone = GaussianBackbone(GaussianConfig(background=background), scene)
        features = backbone.render_ldr_features(camera)
        image = features.composite(features.colors)
        projected = project_gaussians(
            backbone.means,
            backbone.quats,
            torch.exp(backbone.log_scales),
            torch.sigmoid(backbone.opacity_logits),
            camera,
        )
        assert features.colors.shape[0] == projected.index.numel()
        assert torch.equal(image, rasterize(projected, features.colors)[0])
        assert [g["name"] for g in backbone.parameter_groups()][-1] == "opacity_logits"


class TestInitialisation:
    def test_random_points_of_an_unbounded_scene_are_in_view(self):
        scene = make_scene(points=None)
        scene.bounds_min, scene.bounds_max = -torch.full((3,), 6.0), torch.full((3,), 6.0)  # reaches behind
        backbone = GaussianBackbone(GaussianConfig(random_init_points=400), scene)
        means = backbone.means.detach()
        assert means.shape == (400, 3)
        assert ((means >= -6) & (means <= 6)).all()
        seen = torch.zeros(400, dtype=torch.bool)
        for camera in scene.train_cameras:
            pixels, depth = camera.project(means)
            inside = (pixels >= 0).all(-1) & (pixels[:, 0] < camera.width) & (pixels[:, 1] < camera.height)
            seen |= inside & (depth > camera.near)
        assert seen.all()


@pytest.mark.slow
def test_short_run_keeps_the_sun(tmp_path):
    """(g) 1000 cpu-preset steps of mono on the tiny outdoor capture (about 30 s on 2 cores):
    with the environment the sun's HDR peak reaches the GT's order of magnitude in every test view;
    the old model (scene taken as bounded: random points in the box, no sky) keeps about 1 % of it.
    Measured: 0.36-1.25 with, 0.005-0.014 without (deterministic since the rasteriser's backward
    sums in a fixed order); the weakest view moved between 0.21 and 0.74 with the last bits of the
    sums under the old dynamic schedule, so the bounds sit at an order of magnitude either side. On an
    AMD EPYC machine (2026-12-06) the old model's worst view kept 5.4 % (the sums differ by CPU), so its
    bound is 0.1, still 4x below the weakest view with the environment there (0.45)."""
    from gs_outdoor import outdoor_capture, sun_pixels

    from backbones.gs.model import cpu_preset
    from mono_hdr_plugin.training.trainer import Trainer

    ratios = {}
    for unbounded in (True, False):
        torch.manual_seed(0)
        scene = outdoor_capture(unbounded=unbounded)
        config = quiet_config(cpu_preset(), tmp_path / str(unbounded), "mono", max_steps=1000)
        trainer = Trainer(config, "gs", scene)
        trainer.fit()
        trainer.calibrate()
        ratios[unbounded] = []
        with trainer.pipeline.evaluating():
            for view in scene.test:
                frame = trainer.pipeline.render(view.camera, view.exposure)
                sun = sun_pixels(view.camera)
                assert not unbounded or float(frame.ldr[sun].max()) >= 0.95, "the sun is clipped in LDR"
                ratios[unbounded].append(float(frame.hdr[sun].max()) / float(view.hdr.max()))
    assert min(ratios[True]) > 0.1, ratios
    assert max(ratios[False]) < 0.1, ratios
