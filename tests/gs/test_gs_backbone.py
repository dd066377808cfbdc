"""GaussianBackbone: initialisation, presets, rendering interface, schedules, PLY."""

import dataclasses
import math
from pathlib import Path

import pytest
import torch
from gs_scenes import make_camera
from plyfile import PlyParseError

from backbones.gs import (
    DefaultStrategy,
    GaussianBackbone,
    GaussianConfig,
    McmcStrategy,
    export_ply,
    load_ply,
    render_gaussians,
)
from backbones.gs.sh import visible_colors
from mono_hdr_plugin.core.backbone import SceneInfo
from mono_hdr_plugin.core.cameras import look_at
from mono_hdr_plugin.methods.base import MethodConfig
from mono_hdr_plugin.methods.mono import MonoHDR


def make_scene(points: int | None = 300, seed: int = 0) -> SceneInfo:
    gen = torch.Generator().manual_seed(seed)
    base = make_camera()
    cameras = [
        dataclasses.replace(base, c2w=look_at(torch.tensor(eye), torch.zeros(3)))
        for eye in ([0.3, -4.0, 0.5], [3.0, -3.0, 0.4], [-3.0, -3.0, 0.6])
    ]
    scene = SceneInfo(bounds_min=-torch.ones(3), bounds_max=torch.ones(3), train_cameras=cameras)
    if points:
        scene.points = torch.rand(points, 3, generator=gen) * 1.6 - 0.8
        scene.point_colors = (torch.rand(points, 3, generator=gen) * 255).to(torch.uint8)
    return scene


def hide_some(backbone: GaussianBackbone, camera, rows: int = 30) -> None:
    """Move the first `rows` Gaussians behind `camera`, so it culls them."""
    with torch.no_grad():
        backbone.means[:rows] = camera.center - (1.0 + torch.rand(rows, 1)) * camera.c2w[:3, 2]


def make_optimizer(backbone: GaussianBackbone) -> torch.optim.Adam:
    return torch.optim.Adam(backbone.parameter_groups(), eps=1e-15)


def train_step(backbone, optimizer, camera, target, step):
    features = backbone.render_ldr_features(camera)
    image = features.composite(features.colors)
    loss = (image - target).abs().mean() + sum(backbone.regularisation().values(), torch.tensor(0.0))
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    backbone.after_step(step, features, optimizer)
    return loss.item()


class TestInitialisation:
    @pytest.mark.parametrize("backend,builds", [("kernel", 1), ("torch", 0)])
    def test_the_kernel_is_built_at_construction(self, monkeypatch, backend, builds):
        # A first build takes a minute: inside the first step it would count as training time.
        calls = []
        monkeypatch.setattr("backbones.gs.model.load_extension", lambda: calls.append(1))
        GaussianBackbone(GaussianConfig(backend=backend), make_scene(points=20))
        assert len(calls) == builds

    def test_from_points_and_colours(self):
        scene = make_scene(points=200)
        backbone = GaussianBackbone(GaussianConfig(), scene)
        assert backbone.num_gaussians == 200
        torch.testing.assert_close(backbone.means.detach(), scene.points)
        camera = scene.train_cameras[0]
        features = backbone.render_ldr_features(camera)
        index = features.extras["projected"].index
        assert index.numel() > 100
        torch.testing.assert_close(features.colors, scene.point_colors[index].float() / 255, rtol=0, atol=1e-5)
        assert backbone.sh_rest.shape == (200, 15, 3)
        assert (backbone.log_scales.exp() > 0).all() and torch.isfinite(backbone.log_scales).all()

    def test_initial_scale_follows_point_spacing(self):
        """init_scale times the RMS distance to the 3 nearest points: a regular grid of spacing d gives d."""
        grid = torch.stack(torch.meshgrid(*[torch.arange(6.0) * 0.1] * 3, indexing="ij"), -1).reshape(-1, 3)
        scene = make_scene(points=None)
        scene.points = grid - 0.25
        backbone = GaussianBackbone(GaussianConfig(init_scale=0.5), scene)
        inner = ((grid > 0.05) & (grid < 0.45)).all(-1)  # points with 6 neighbours at distance 0.1
        torch.testing.assert_close(backbone.log_scales.exp()[inner], torch.full((int(inner.sum()), 3), 0.05))

    def test_points_beyond_the_budget_are_subsampled(self):
        scene = make_scene(points=300)
        backbone = GaussianBackbone(GaussianConfig(strategy=McmcStrategy(max_gaussians=120)), scene)
        assert backbone.num_gaussians == backbone.budget == 120
        rows = (backbone.means.detach()[:, None, :] == scene.points[None]).all(-1)
        assert (rows.sum(1) == 1).all(), "every Gaussian starts on one of the given points"

    def test_random_inside_bounds(self):
        backbone = GaussianBackbone(GaussianConfig(random_init_points=500), make_scene(points=None))
        assert backbone.num_gaussians == 500
        assert backbone.means.abs().max() <= 1.0

    def test_budget_follows_the_training_pixels(self):
        scene = make_scene(points=None)
        pixels = sum(c.width * c.height for c in scene.train_cameras)
        backbone = GaussianBackbone(GaussianConfig(strategy=McmcStrategy(gaussians_per_pixel=0.25)), scene)
        assert backbone.budget == int(0.25 * pixels) and backbone.num_gaussians <= backbone.budget

    def test_rejects_bad_config(self):
        with pytest.raises(ValueError, match="SH degree"):
            GaussianBackbone(GaussianConfig(sh_degree=4), make_scene())
        with pytest.raises(ValueError, match="backend"):
            GaussianBackbone(GaussianConfig(backend="cuda"), make_scene())
        with pytest.raises(ValueError, match="--backbone.strategy.max-gaussians"):
            GaussianBackbone(GaussianConfig(strategy=McmcStrategy(max_gaussians=0)), make_scene())
        scene = make_scene()
        scene.point_colors = scene.point_colors[:5]
        with pytest.raises(ValueError, match="point_colors"):
            GaussianBackbone(GaussianConfig(), scene)

    @pytest.mark.parametrize("config_class", [GaussianConfig, McmcStrategy, DefaultStrategy])
    def test_config_fields_documented(self, config_class):
        source = Path(config_class.__module__.replace(".", "/") + ".py").read_text()
        body = source.split(f"class {config_class.__name__}", 1)[1]
        for f in dataclasses.fields(config_class):
            after = body.split(f"    {f.name}:", 1)[1].splitlines()[1].strip()
            assert after.startswith('"""'), f"field {f.name} needs a docstring line for tyro"


class TestPresets:
    def test_cpu_first_then_paper(self):
        presets = GaussianBackbone.presets()
        assert list(presets) == ["cpu", "paper"]
        assert isinstance(presets["cpu"].strategy, McmcStrategy)
        assert presets["paper"] == GaussianConfig() and isinstance(presets["paper"].strategy, DefaultStrategy)

    def test_paper_preset_is_the_official_recipe(self):
        paper = GaussianBackbone.presets()["paper"]
        assert (paper.lr_means, paper.lr_sh_dc, paper.lr_opacities, paper.lr_scales, paper.lr_quats) == (
            1.6e-4,
            2.5e-3,
            0.05,
            5e-3,
            1e-3,
        )
        assert (paper.strategy.grad_threshold, paper.strategy.refine_stop, paper.sh_increase_every) == (
            2e-4,
            15_000,
            1000,
        )


class TestRenderLdrFeatures:
    def test_shapes_and_extras(self):
        scene = make_scene()
        backbone = GaussianBackbone(GaussianConfig(), scene)
        camera = scene.train_cameras[0]
        hide_some(backbone, camera)
        features = backbone.render_ldr_features(camera)
        projected = features.extras["projected"]
        visible = projected.index.numel()
        assert 0 < visible < backbone.num_gaussians, "the test scene has culled Gaussians"
        assert features.colors.shape == (visible, 3) and features.raw_colors.shape == (visible, 3)
        assert (features.colors >= 0).all()
        torch.testing.assert_close(features.colors, (features.raw_colors + 0.5).clamp_min(0))
        assert "alpha" not in features.extras, "nothing is rasterised before composite is called"
        image = features.composite(torch.cat([features.colors, features.colors * 2], -1))
        assert image.shape == (camera.height, camera.width, 6)
        torch.testing.assert_close(image[..., 3:], 2 * image[..., :3], rtol=1e-5, atol=1e-6)
        assert features.extras["alpha"].shape == (camera.height, camera.width, 1)
        assert projected.means2d.shape == (visible, 2) and projected.radii.shape == (backbone.num_gaussians,)

    def test_depth_only_when_asked(self):
        scene = make_scene()
        backbone = GaussianBackbone(GaussianConfig(), scene)
        camera = scene.train_cameras[0]
        features = backbone.render_ldr_features(camera)
        depth = features.extras["render_depth"]()
        hit = features.composite(features.colors.new_ones(features.colors.shape[0], 1)) > 0.5
        assert depth.shape == (camera.height, camera.width, 1)
        distance = (backbone.means.detach() - camera.center).norm(dim=-1)
        assert ((depth[hit] > 0.5 * distance.min()) & (depth[hit] < distance.max())).all()

    def test_renders_get_the_depth_pass_when_asked(self):
        """Pipeline.render(with_depth=True) (viewer depth, videos, point clouds) runs the render_depth
        pass, with the composite's alpha beside it; evaluation's renders skip it."""
        from mono_hdr_plugin.training.pipeline import Pipeline

        scene = make_scene()
        backbone = GaussianBackbone(GaussianConfig(), scene).eval()
        pipeline = Pipeline("gs", backbone, MonoHDR(MethodConfig(), backbone.loss_kind)).eval()
        camera = scene.train_cameras[0]
        frame = pipeline.render(camera, 1.0, with_depth=True)
        assert pipeline.render(camera, 1.0).depth is None
        with torch.no_grad():
            features = backbone.render_ldr_features(camera)
            depth = features.extras["render_depth"]()
            features.composite(features.colors)
        torch.testing.assert_close(frame.depth, depth[..., 0])
        torch.testing.assert_close(frame.alpha, features.extras["alpha"][..., 0])
        assert (frame.depth > 0).any()

    def test_converter_on_visible_gaussians_renders_as_on_all(self):
        """The method's L2H-CC on the V visible Gaussians gives the image that running it on all N
        and compositing every Gaussian gives."""
        torch.manual_seed(0)
        scene = make_scene(points=400)
        backbone = GaussianBackbone(GaussianConfig(), scene)
        backbone.active_sh_degree = 3
        with torch.no_grad():
            backbone.sh_rest.normal_(0, 0.2)
        method = MonoHDR(MethodConfig(), "l1_dssim")
        camera = scene.train_cameras[1]
        hide_some(backbone, camera)
        features = backbone.render_ldr_features(camera)
        output = method(features, 1.0)
        everyone = torch.arange(backbone.num_gaussians)
        assert features.colors.shape[0] < everyone.numel()
        colors = (
            visible_colors(3, backbone.sh_dc, backbone.sh_rest, backbone.means, everyone, camera.center) + 0.5
        ).clamp_min(0)
        values = torch.cat([colors, method.l2h(colors)], -1)
        image, _, _ = render_gaussians(
            backbone.means,
            backbone.quats,
            torch.exp(backbone.log_scales),
            torch.sigmoid(backbone.opacity_logits),
            values,
            camera,
        )
        assert output.hdr.max() > 0.1
        torch.testing.assert_close(output.ldr, image[..., :3], rtol=0, atol=0)
        torch.testing.assert_close(output.hdr, image[..., 3:], rtol=0, atol=0)

    def test_two_training_steps_lower_the_loss(self):
        scene = make_scene()
        backbone = GaussianBackbone(GaussianConfig(), scene)
        backbone.set_run_length(100)
        optimizer = make_optimizer(backbone)
        camera = scene.train_cameras[0]
        target = torch.full((camera.height, camera.width, 3), 0.8)
        losses = [train_step(backbone, optimizer, camera, target, step) for step in range(6)]
        assert losses[-1] < losses[0]
        assert torch.isfinite(backbone.means).all()


class TestSchedules:
    def test_position_decay_endpoints(self):
        backbone = GaussianBackbone(GaussianConfig(), make_scene())
        backbone.set_run_length(1000)
        base = backbone.parameter_groups()[0]["lr"]
        assert backbone.learning_rate("means", 0, base) == pytest.approx(base)
        assert backbone.learning_rate("means", 1000, base) == pytest.approx(base / 100)
        assert base / 100 < backbone.learning_rate("means", 500, base) < base
        assert backbone.learning_rate("sh_dc", 500, 0.1) == 0.1

    def test_groups_named_and_complete(self):
        backbone = GaussianBackbone(GaussianConfig(), make_scene())
        groups = backbone.parameter_groups()
        assert [g["name"] for g in groups] == ["means", "sh_dc", "sh_rest", "log_scales", "quats", "opacity_logits"]
        assert sum(p.numel() for g in groups for p in g["params"]) == sum(p.numel() for p in backbone.parameters())

    def test_repeated_run_length_estimates_rescale_and_keep_state(self):
        """--max-seconds calls set_run_length again and again: the SH degree never drops, the
        strategy statistics survive, and the schedules follow the latest length."""
        scene = make_scene()
        backbone = GaussianBackbone(GaussianConfig(), scene)
        optimizer = make_optimizer(backbone)
        camera = scene.train_cameras[0]
        target = torch.full((camera.height, camera.width, 3), 0.5)
        backbone.set_run_length(90)  # SH degree +1 every 3 steps, refine every 10
        for step in range(7):
            train_step(backbone, optimizer, camera, target, step)
        assert backbone.active_sh_degree == 2
        statistics = {k: v.clone() for k, v in backbone.strategy_state.items()}
        assert statistics["visible_count"].max() == 7
        for estimate in (3000, 120, 30_000):
            backbone.set_run_length(estimate)
            for name, value in statistics.items():
                torch.testing.assert_close(backbone.strategy_state[name], value)
        train_step(backbone, optimizer, camera, target, 7)  # a 30k estimate: degree 2 would be "too early"
        assert backbone.active_sh_degree == 2
        assert backbone.config.strategy.schedule(backbone.max_steps).every == 100
        backbone.set_run_length(300)
        assert backbone.config.strategy.schedule(backbone.max_steps).every == 10
        base = backbone.parameter_groups()[0]["lr"]
        assert backbone.learning_rate("means", 300, base) == pytest.approx(base / 100)


class TestPly:
    def test_round_trip(self, tmp_path):
        scene = make_scene()
        backbone = GaussianBackbone(GaussianConfig(), scene)
        with torch.no_grad():
            backbone.sh_rest.normal_()
            backbone.quats.normal_()
        path = export_ply(backbone, tmp_path / "model" / "point_cloud.ply")
        assert not list(path.parent.glob("*.tmp")), "temporary file left behind"
        loaded = load_ply(path)
        for name, tensor in loaded.items():
            torch.testing.assert_close(tensor, getattr(backbone, name).detach(), rtol=0, atol=0, msg=name)
        other = GaussianBackbone(GaussianConfig(random_init_points=10), make_scene(points=None))
        other.load_gaussians(loaded)
        camera = scene.train_cameras[0]
        backbone.active_sh_degree = other.active_sh_degree = 3
        a = backbone.render_ldr_features(camera)
        b = other.render_ldr_features(camera)
        torch.testing.assert_close(b.composite(b.colors), a.composite(a.colors))
        assert other.strategy_state["grad2d_sum"].shape == (backbone.num_gaussians,)

    def test_standard_attribute_names(self, tmp_path):
        from plyfile import PlyData

        backbone = GaussianBackbone(GaussianConfig(), make_scene(points=20))
        names = PlyData.read(str(export_ply(backbone, tmp_path / "a.ply")))["vertex"].data.dtype.names
        assert names[:9] == ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
        assert names[9:54] == tuple(f"f_rest_{i}" for i in range(45))
        assert names[54:] == ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")

    def test_rejects_non_splat_files(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="no PLY"):
            load_ply(tmp_path / "missing.ply")
        (tmp_path / "junk.ply").write_text("not a ply")
        with pytest.raises(PlyParseError):
            load_ply(tmp_path / "junk.ply")


def test_log_of_init_opacity_is_a_logit():
    backbone = GaussianBackbone(GaussianConfig(init_opacity=0.3), make_scene(points=10))
    torch.testing.assert_close(torch.sigmoid(backbone.opacity_logits), torch.full((10,), 0.3))
    assert math.isclose(backbone.budget, DefaultStrategy().max_gaussians)
