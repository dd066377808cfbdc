"""The 3DGS backbone with sky Gaussians behind its splats (--backbone.background sky-gaussians)."""

import dataclasses
import math

import numpy as np
import pytest
import torch
from gs_outdoor import outdoor_capture
from helpers import quiet_config
from test_gs_sky import adam_state, descend, hand_directions, make_scene

from backbones.gs import DefaultStrategy, GaussianBackbone, GaussianConfig, McmcStrategy
from backbones.gs.ply import load_ply
from backbones.gs.sky import seen_by_cameras
from backbones.gs.sky_gaussians import (
    SkyGaussians,
    fibonacci_directions,
    scene_projection,
    shell_centre,
    shell_directions,
    shell_radius,
)
from mono_hdr_plugin.core.backbone import SceneInfo
from mono_hdr_plugin.core.cameras import look_at
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


def looking_at(target, *eyes, parallel: bool = False) -> SceneInfo:
    """A scene box [-5, -4, -3] .. [1, 1, 1] (centre (-2, -1.5, -1)) seen by cameras at `eyes` looking at
    `target`, or with `parallel` each along the direction `target` (eye + target)."""
    base = make_scene(points=None).train_cameras[0]
    cameras = []
    for eye in map(torch.tensor, eyes):
        aim = eye + torch.tensor(target) if parallel else torch.tensor(target)
        cameras.append(dataclasses.replace(base, c2w=look_at(eye, aim)))
    return SceneInfo(torch.tensor([-5.0, -4.0, -3.0]), torch.ones(3), cameras, unbounded=True)


class TestShellGeometry:
    """The shell's directions, centre and radius against values computed here another way."""

    def test_fibonacci_directions_by_hand(self):
        golden_angle = 2 * math.pi * (1 - 2 / (1 + math.sqrt(5)))  # 2 pi (1 - 1 / phi)
        count = 7
        expected = []
        for i in range(count):
            z = 1 - (2 * i + 1) / count
            ring = math.sqrt(1 - z * z)
            angle = (i + 0.5) * golden_angle
            expected.append([ring * math.cos(angle), ring * math.sin(angle), z])
        torch.testing.assert_close(fibonacci_directions(count), torch.tensor(expected), atol=1e-6, rtol=0)

    def test_the_centre_is_where_the_optical_axes_meet(self):
        """Least squares over the axes plus a pull of weight 1e-3 per camera towards the box centre,
        solved here with numpy's lstsq on the stacked rows."""
        scene = looking_at([2.0, 1.0, 0.5], [2.0, -6.0, 1.0], [9.0, 1.5, 0.0], [-3.0, 6.0, 2.5])
        rows, rhs = [], []
        for camera in scene.train_cameras:
            axis = camera.c2w[:3, 2].double().numpy()
            projector = np.eye(3) - np.outer(axis, axis)
            rows.append(projector)
            rhs.append(projector @ camera.center.double().numpy())
        pull = math.sqrt(1e-3 * len(scene.train_cameras))
        rows.append(pull * np.eye(3))
        rhs.append(pull * np.array([-2.0, -1.5, -1.0]))
        expected = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)[0]
        np.testing.assert_allclose(shell_centre(scene).numpy(), expected, atol=1e-5)
        assert np.linalg.norm(expected - [2.0, 1.0, 0.5]) < 0.01, "the pull is weak"

    def test_parallel_axes_take_the_box_centre_along_them(self):
        # all along +y: across the axes the mean camera position, along them the box centre's y
        scene = looking_at([0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 3.0], parallel=True)
        torch.testing.assert_close(shell_centre(scene), torch.tensor([0.0, -1.5, 1.0]), atol=5e-3, rtol=0)
        assert torch.equal(shell_centre(dataclasses.replace(scene, train_cameras=[])), torch.tensor([-2.0, -1.5, -1.0]))

    def test_a_shell_no_camera_sees_is_the_whole_sphere(self):
        scene = looking_at([0.0, 0.0, 0.0], [0.0, -6.0, 0.0])
        blind = [dataclasses.replace(camera, near=1e4, far=1e5) for camera in scene.train_cameras]  # beyond the shell
        directions, sphere = shell_directions(300, torch.zeros(3), 80.0, blind)
        assert sphere == 300
        torch.testing.assert_close(directions, fibonacci_directions(300))

    def test_each_gaussian_spans_its_share_of_the_sphere(self):
        """Without cameras the shell is the whole sphere: S Gaussians on radius R each cover 4 pi R^2 / S,
        and their scale is `scale` times the square root of that."""
        scene = SceneInfo(-torch.ones(3), torch.ones(3), [], unbounded=True)
        sky = SkyGaussians(scene, 200, 0.7)
        radius = 10 * math.sqrt(3)  # the box's corners, from its centre
        torch.testing.assert_close((sky.means - scene.center).norm(dim=-1), torch.full((200,), radius))
        torch.testing.assert_close(sky.scales, torch.full((200,), 0.7 * math.sqrt(4 * math.pi * radius**2 / 200)))

    def test_the_radius_is_ten_times_the_farthest_corner_or_camera(self):
        # from the origin the farthest corner is the box's low one, (-5, -4, -3): sqrt(50)
        scene = looking_at([0.0, 0.0, 0.0], [0.0, -6.0, 0.0])
        assert shell_radius(scene, torch.zeros(3)) == pytest.approx(10 * math.sqrt(50))
        far = looking_at([0.0, 0.0, 0.0], [0.0, -9.0, 0.0])  # a camera farther than every corner
        assert shell_radius(far, torch.zeros(3)) == pytest.approx(90.0)
        # about another point: the corner (1, 1, 1) is sqrt(3) x 7 from (-6, -6, -6); the camera 6 sqrt(3)
        assert shell_radius(scene, torch.full((3,), -6.0)) == pytest.approx(10 * 7 * math.sqrt(3))


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

    def test_a_viewer_sees_the_skys_colours_opaque_and_round(self, tmp_path):
        """What a 3DGS viewer computes from the PLY: colour 0.5 + Y00 f_dc (Y00 = 1 / (2 sqrt(pi))), opacity
        sigmoid(logit), scales exp(log scale), rotation the normalised quaternion."""
        backbone = sky_backbone(make_scene(points=40))
        count = backbone.sky.count
        with torch.no_grad():
            backbone.sky.colors.copy_(torch.rand(count, 3, generator=torch.Generator().manual_seed(3)) - 0.5)
        backbone.export_ply(tmp_path / "model.ply")
        sky = load_ply(tmp_path / "model.sky.ply")
        y00 = 1 / (2 * math.sqrt(math.pi))
        torch.testing.assert_close(0.5 + y00 * sky["sh_dc"][:, 0], backbone.sky.colors.detach() + 0.5)
        torch.testing.assert_close(torch.sigmoid(sky["opacity_logits"]), torch.full((count,), 0.9999))
        torch.testing.assert_close(sky["log_scales"].exp(), backbone.sky.scales[:, None].expand(count, 3))
        quats = sky["quats"] / sky["quats"].norm(dim=-1, keepdim=True)
        torch.testing.assert_close(quats, torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(count, 4))


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
