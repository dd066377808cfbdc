"""The 3DGS backbone with sky Gaussians behind its splats (--backbone.background sky-gaussians)."""

import math

import pytest
import torch
from gs_outdoor import outdoor_capture
from helpers import quiet_config
from test_gs_sky import adam_state, descend, hand_directions, make_scene

from backbones.gs import DefaultStrategy, GaussianBackbone, GaussianConfig, McmcStrategy
from backbones.gs.ply import load_ply
from backbones.gs.sky import seen_by_cameras
from backbones.gs.sky_gaussians import fibonacci_directions, scene_projection, shell_centre
from mono_hdr_plugin.core.validation import FlagError, check_flags
from mono_hdr_plugin.training.trainer import Trainer


def sky_backbone(scene, **overrides) -> GaussianBackbone:
    return GaussianBackbone(GaussianConfig(background="sky-gaussians", sky_gaussians=512, **overrides), scene)


class TestChoiceAndPlacement:
    def test_only_when_asked(self):
        assert GaussianBackbone(GaussianConfig(), make_scene()).sky is None  # auto: the environment map
        backbone = sky_backbone(make_scene())
        assert backbone.environment is None and backbone.sky is not None
        assert backbone.num_gaussians == 200, "the sky is not counted among the scene's Gaussians"
        assert "sky" not in {g["name"] for g in backbone.parameter_groups()[:6]}
        assert [g["name"] for g in backbone.parameter_groups()][-1] == "sky"

    def test_flag_rules(self):
        check_flags(GaussianConfig(background="sky-gaussians"))
        for field, value in (("sky_gaussians", 0), ("sky_scale", 0.0), ("lr_sky", 0.0)):
            with pytest.raises(FlagError, match="--" + field.replace("_", "-")):
                check_flags(GaussianConfig(**{field: value}))

    def test_even_shell_over_the_seen_directions_behind_the_scene(self):
        scene = make_scene()
        sky = sky_backbone(scene).sky
        assert abs(sky.count - 512) <= 0.02 * 512, "the count is spent on the directions the cameras see"
        assert seen_by_cameras(sky.means, scene.train_cameras, 0.1).all()
        for camera in scene.train_cameras:  # radius: ten times the farthest camera or box corner
            depth = (sky.means - camera.center).norm(dim=-1)
            assert float(depth.min()) > 5 * float((scene.points - camera.center).norm(dim=-1).max())
        assert torch.equal(sky.colors, torch.zeros_like(sky.colors)), "mid grey, as the environment map starts"
        directions = fibonacci_directions(1000)
        torch.testing.assert_close(directions.norm(dim=-1), torch.ones(1000))
        assert directions.mean(0).norm() < 0.01, "spread evenly"


class TestCoverage:
    """(b) with nothing in front the sky fills every training view; splats composite over it."""

    def test_sky_covers_every_training_view(self):
        scene = make_scene(points=None)
        backbone = sky_backbone(scene)
        with torch.no_grad():
            backbone.opacity_logits.fill_(-30.0)  # no foreground
        for camera in scene.train_cameras:
            features = backbone.render_ldr_features(camera)
            image = features.composite(features.colors)
            assert float(features.extras["alpha"].detach().min()) > 0.98
            torch.testing.assert_close(image, torch.full_like(image, 0.5), atol=0.01, rtol=0)
            assert float(features.extras["render_depth"]().detach().abs().max()) == 0.0, "the sky has no depth"

    def test_each_direction_shows_its_own_colour(self):
        """A sky whose colour varies with direction (raw 0.3 d: LDR 0.5 + 0.3 d) renders each pixel the
        colour of the direction where its ray meets the shell: a colour drawn at another Gaussian's
        place is off by up to 0.6."""
        scene = make_scene(points=None)
        backbone = sky_backbone(scene)
        centre = shell_centre(scene)
        radius = float((backbone.sky.means[0] - centre).norm())
        with torch.no_grad():
            backbone.opacity_logits.fill_(-30.0)  # no foreground
            backbone.sky.colors.copy_(0.3 * (backbone.sky.means - centre) / radius)
        for camera in scene.train_cameras:
            features = backbone.render_ldr_features(camera)
            image = features.composite(features.colors).detach()
            rays = hand_directions(camera)
            offset = camera.center - centre  # where each ray leaves the sphere |o + t d - centre| = radius
            along = rays @ offset
            t = -along + (along**2 - float(offset @ offset) + radius**2).sqrt()
            alpha = features.extras["alpha"].detach().reshape(image.shape[:2])[..., None]  # 0.98-1: over black
            expected = (0.5 + 0.3 * (offset + t[..., None] * rays) / radius) * alpha
            error = (image - expected).abs()
            assert float(error.mean()) < 0.025 and float(error.max()) < 0.06, (error.mean(), error.max())

    def test_scene_in_front_of_the_sky(self):
        scene = make_scene(points=200)
        backbone = sky_backbone(scene)
        with torch.no_grad():
            backbone.opacity_logits.fill_(8.0)
            backbone.sky.colors.fill_(5.0)  # a bright sky: any of it in front of a splat would show
        camera = scene.train_cameras[0]
        features = backbone.render_ldr_features(camera)
        projected = features.extras["projected"]
        is_sky = projected.index >= backbone.num_gaussians
        assert is_sky.any() and (~is_sky).any()
        depths = projected.depths.detach()
        assert float(depths[is_sky].min()) > float(depths[~is_sky].max())
        depth = features.extras["render_depth"]().detach()
        covered = depth[..., 0] > 0
        assert covered.any()
        assert float(depth.max()) < 10.0, "depth is the scene's, not the sky's"


STRATEGIES = [
    DefaultStrategy(refine_start=0, refine_every=1, min_refine_every=1, grad_threshold=0.0, reset_opacity_every=2),
    McmcStrategy(refine_start=0, refine_every=1, min_refine_every=1, grow_fraction=0.5, min_opacity=0.3),
]


class TestDensityControlLeavesTheSkyAlone:
    """(a) refinement, pruning, opacity reset and relocation edit the scene's Gaussians only."""

    @pytest.mark.parametrize("strategy", STRATEGIES, ids=["default", "mcmc"])
    def test_sky_and_its_adam_state_unchanged(self, strategy):
        scene = make_scene(points=80)
        camera = scene.train_cameras[0]
        backbone = sky_backbone(scene, strategy=strategy)
        backbone.set_run_length(30_000)  # unscaled schedule: refine every step, reset at step 2
        optimizer = torch.optim.Adam(backbone.parameter_groups(), eps=1e-15)
        target = torch.rand(camera.height, camera.width, 3, generator=torch.Generator().manual_seed(2))
        means, scales = backbone.sky.means.clone(), backbone.sky.scales.clone()
        counts = []
        for step in range(1, 5):
            features = descend(backbone, camera, target, optimizer)
            colors, moments = backbone.sky.colors.detach().clone(), adam_state(optimizer, [backbone.sky.colors])
            before = backbone.num_gaussians
            backbone.after_step(step, features, optimizer)
            counts.append((before, backbone.num_gaussians))
            group = next(g for g in optimizer.param_groups if g["name"] == "sky")
            assert group["params"][0] is backbone.sky.colors
            assert torch.equal(backbone.sky.colors, colors)
            assert all(torch.equal(optimizer.state[backbone.sky.colors][k], v) for k, v in moments[0].items())
            assert torch.equal(backbone.sky.means, means) and torch.equal(backbone.sky.scales, scales)
            for state in backbone.strategy_state.values():
                assert state.shape[0] == backbone.num_gaussians
        assert any(a != b for a, b in counts), "density control ran and changed the Gaussians"
        assert not torch.equal(colors, torch.zeros_like(colors)), "the sky's colours learn"

    def test_strategy_sees_the_scene_rows_only(self):
        scene = make_scene(points=80)
        backbone = sky_backbone(scene)
        features = backbone.render_ldr_features(scene.train_cameras[0])
        features.composite(features.colors).sum().backward()
        projected = features.extras["projected"]
        n = backbone.num_gaussians
        view = scene_projection(projected, n)
        visible = view.index.numel()
        assert 0 < visible < projected.index.numel()
        assert (view.index < n).all() and (projected.index[visible:] >= n).all()
        assert view.radii.shape == (n,) and view.means2d.shape == (visible, 2)
        torch.testing.assert_close(view.means2d.grad, projected.means2d.grad[:visible])


class TestSaving:
    def test_checkpoint_round_trip(self):
        """A fresh backbone whose shell has another size takes the checkpoint's and renders the same."""
        scene = make_scene(points=80)
        camera = scene.train_cameras[1]
        trained = sky_backbone(scene)
        with torch.no_grad():
            trained.sky.colors.copy_(torch.rand(trained.sky.colors.shape) - 0.5)
        fresh = GaussianBackbone(GaussianConfig(background="sky-gaussians", sky_gaussians=200), make_scene(points=30))
        fresh.load_state_dict(trained.state_dict())
        assert fresh.sky.count == trained.sky.count
        expected = trained.render_ldr_features(camera)
        got = fresh.render_ldr_features(camera)
        torch.testing.assert_close(got.composite(got.colors), expected.composite(expected.colors))

    def test_export_writes_the_sky_beside_the_ply(self, tmp_path):
        backbone = sky_backbone(make_scene(points=40))
        ply = backbone.export_ply(tmp_path / "model.ply")
        assert load_ply(ply)["means"].shape[0] == 40, "the scene's PLY holds the scene's Gaussians"
        sky = load_ply(tmp_path / "model.sky.ply")
        torch.testing.assert_close(sky["means"], backbone.sky.means)
        assert sky["sh_rest"].shape == (backbone.sky.count, 0, 3)


def test_two_training_steps_change_the_sky(tmp_path):
    """(c) two real steps of mono on the tiny outdoor capture train the sky's colours."""
    torch.manual_seed(0)
    scene = outdoor_capture()
    backbone_config = GaussianConfig(random_init_points=300, background="sky-gaussians", sky_gaussians=1024)
    trainer = Trainer(quiet_config(backbone_config, tmp_path / "run", "mono", max_steps=2), "gs", scene)
    colors = trainer.backbone.sky.colors.detach().clone()
    records = [trainer.train_step() for _ in range(2)]
    assert all(math.isfinite(r["loss"]) and not r["skipped"] for r in records)
    assert not torch.equal(colors, trainer.backbone.sky.colors)
    assert trainer.backbone.num_gaussians <= 300
