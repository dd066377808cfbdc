"""GaussianBackbone: initialisation, rendering interface, schedules, density control, PLY."""

import dataclasses

import pytest
import torch

from backbones.gs import GaussianBackbone, GaussianConfig, export_ply, load_ply
from gs_scenes import make_camera
from mono_hdr_plugin.backbone import SceneInfo
from mono_hdr_plugin.cameras import look_at


def make_scene(points: int | None = 300, seed: int = 0) -> SceneInfo:
    gen = torch.Generator().manual_seed(seed)
    base = make_camera()
    cameras = [dataclasses.replace(base, c2w=look_at(torch.tensor(eye), torch.zeros(3)))
               for eye in ([0.3, -4.0, 0.5], [3.0, -3.0, 0.4], [-3.0, -3.0, 0.6])]
    scene = SceneInfo(bounds_min=-torch.ones(3), bounds_max=torch.ones(3), train_cameras=cameras)
    if points:
        scene.points = torch.rand(points, 3, generator=gen) * 1.6 - 0.8
        scene.point_colors = (torch.rand(points, 3, generator=gen) * 255).to(torch.uint8)
    return scene


def make_optimizer(backbone: GaussianBackbone) -> torch.optim.Adam:
    return torch.optim.Adam(backbone.parameter_groups(), eps=1e-15)


def train_step(backbone, optimizer, camera, target, step):
    features = backbone.render_ldr_features(camera)
    image = features.composite(features.colors)
    loss = (image - target).abs().mean()
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    backbone.after_step(step, features, optimizer)
    return loss.item()


def assert_optimizer_consistent(backbone, optimizer):
    n = backbone.num_gaussians
    for group in optimizer.param_groups:
        (param,) = group["params"]
        assert param is getattr(backbone, group["name"]), f"{group['name']} not the module's parameter"
        assert param.shape[0] == n, group["name"]
        state = optimizer.state.get(param)
        if state:
            assert state["exp_avg"].shape == param.shape and state["exp_avg_sq"].shape == param.shape


class TestInitialisation:
    def test_from_points_and_colours(self):
        scene = make_scene(points=200)
        backbone = GaussianBackbone(GaussianConfig(), scene)
        assert backbone.num_gaussians == 200
        torch.testing.assert_close(backbone.means.detach(), scene.points)
        camera = scene.train_cameras[0]
        backbone.active_sh_degree = 0
        features = backbone.render_ldr_features(camera)
        torch.testing.assert_close(features.colors, scene.point_colors.float() / 255, rtol=0, atol=1e-5)
        assert backbone.sh_rest.shape == (200, 15, 3)
        assert (backbone.log_scales.exp() > 0).all() and torch.isfinite(backbone.log_scales).all()

    def test_random_inside_bounds(self):
        backbone = GaussianBackbone(GaussianConfig(random_init_points=500), make_scene(points=None))
        assert backbone.num_gaussians == 500
        assert backbone.means.abs().max() <= 1.0

    def test_rejects_bad_config(self):
        with pytest.raises(ValueError, match="SH degree"):
            GaussianBackbone(GaussianConfig(sh_degree=4), make_scene())
        with pytest.raises(ValueError, match="backend"):
            GaussianBackbone(GaussianConfig(backend="cuda"), make_scene())
        scene = make_scene()
        scene.point_colors = scene.point_colors[:5]
        with pytest.raises(ValueError, match="point_colors"):
            GaussianBackbone(GaussianConfig(), scene)

    def test_config_fields_documented(self):
        source = open(GaussianConfig.__module__.replace(".", "/") + ".py").read()
        for f in dataclasses.fields(GaussianConfig):
            after = source.split(f"    {f.name}:", 1)[1].splitlines()[1].strip()
            assert after.startswith('"""'), f"field {f.name} needs a docstring line for tyro"


class TestRenderLdrFeatures:
    def test_shapes_and_extras(self):
        scene = make_scene()
        backbone = GaussianBackbone(GaussianConfig(), scene)
        camera = scene.train_cameras[0]
        features = backbone.render_ldr_features(camera)
        n = backbone.num_gaussians
        assert features.colors.shape == (n, 3) and features.raw_colors.shape == (n, 3)
        assert (features.colors >= 0).all()
        torch.testing.assert_close(features.colors, (features.raw_colors + 0.5).clamp_min(0))
        image = features.composite(torch.cat([features.colors, features.colors * 2], -1))
        assert image.shape == (camera.height, camera.width, 6)
        torch.testing.assert_close(image[..., 3:], 2 * image[..., :3], rtol=1e-5, atol=1e-6)
        assert features.extras["alpha"].shape == (camera.height, camera.width, 1)
        assert features.extras["depth"].shape == (camera.height, camera.width, 1)
        assert features.extras["means2d"].shape == (n, 2)
        assert features.extras["radii"].shape == (n,) and features.extras["radii"].max() > 0

    def test_alpha_available_before_composite(self):
        scene = make_scene()
        backbone = GaussianBackbone(GaussianConfig(), scene)
        features = backbone.render_ldr_features(scene.train_cameras[0])
        assert "alpha" in features.extras
        alpha_first = features.extras["alpha"].clone()
        features.composite(features.colors)
        torch.testing.assert_close(features.extras["alpha"], alpha_first)
        assert alpha_first.max() > 0.1

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


class TestLearningRate:
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
        assert {g["name"] for g in groups} == {"means", "sh_dc", "sh_rest", "log_scales", "quats", "opacity_logits"}
        assert sum(p.numel() for g in groups for p in g["params"]) == sum(p.numel() for p in backbone.parameters())


class TestDensityControl:
    def _trained(self, **config):
        scene = make_scene()
        backbone = GaussianBackbone(GaussianConfig(**config), scene)
        backbone.set_run_length(300)
        optimizer = make_optimizer(backbone)
        camera = scene.train_cameras[0]
        target = torch.rand(camera.height, camera.width, 3, generator=torch.Generator().manual_seed(1))
        return backbone, optimizer, camera, target

    def test_clone_and_split_keep_optimizer_aligned(self):
        backbone, optimizer, camera, target = self._trained(prune_opacity=0.0)
        train_step(backbone, optimizer, camera, target, 0)  # fills Adam's moments
        n = backbone.num_gaussians
        for group in optimizer.param_groups:  # tag each row's moments with its row number
            rows = torch.arange(n, dtype=torch.float32).reshape(-1, *[1] * (group["params"][0].dim() - 1))
            optimizer.state[group["params"][0]]["exp_avg"] = rows.expand_as(group["params"][0]).clone()
        with torch.no_grad():
            backbone.log_scales[:4] = -8.0   # small: cloned
            backbone.log_scales[4:8] = -0.5  # large: split
        old_means = backbone.means.detach().clone()
        old_scales = backbone.log_scales.detach().clone()
        control = backbone.density_control
        control.state = type(control.state).empty(n)  # forget step 0's real gradients
        means2d = torch.zeros(n, 2, requires_grad=True)
        means2d.grad = torch.zeros(n, 2)
        means2d.grad[:8] = 1.0  # only rows 0..7 exceed the gradient threshold
        step = control.schedule.refine_every * (control.schedule.refine_start // control.schedule.refine_every + 1)
        control.step_post_backward(backbone, optimizer, step, means2d, torch.ones(n, dtype=torch.int32),
                                   camera.width, camera.height)

        assert backbone.num_gaussians == n + 4 + 4  # 4 clones, 4 splits into 2
        assert_optimizer_consistent(backbone, optimizer)
        tags = optimizer.state[backbone.means]["exp_avg"][:, 0]
        survivors = [i for i in range(n) if not 4 <= i < 8]
        torch.testing.assert_close(tags[:n - 4], torch.tensor(survivors, dtype=torch.float32))
        torch.testing.assert_close(backbone.means.detach()[:n - 4], old_means[survivors])
        assert tags[n - 4:].abs().max() == 0, "new rows start with zero moments"
        torch.testing.assert_close(backbone.means.detach()[n - 4:n], old_means[:4])  # clones
        torch.testing.assert_close(backbone.log_scales.detach()[n:], (old_scales[4:8] - torch.log(torch.tensor(1.6))).repeat(2, 1))
        train_step(backbone, optimizer, camera, target, step + 1)  # Adam still steps
        assert torch.isfinite(backbone.means).all()

    def test_prune_removes_transparent_rows(self):
        backbone, optimizer, camera, target = self._trained(grad_threshold=1e9)
        with torch.no_grad():
            backbone.opacity_logits[:50] = -20.0
        keep_means = backbone.means.detach()[50:].clone()
        schedule = backbone.density_control.schedule
        step = schedule.refine_every * (schedule.refine_start // schedule.refine_every + 1)
        train_step(backbone, optimizer, camera, target, step - 1)
        moment = optimizer.state[backbone.means]["exp_avg"][50:].clone()
        train_step(backbone, optimizer, camera, target, step)
        assert backbone.num_gaussians == keep_means.shape[0]
        assert_optimizer_consistent(backbone, optimizer)
        assert moment.shape == optimizer.state[backbone.means]["exp_avg"].shape

    def test_opacity_reset_clears_moments(self):
        backbone, optimizer, camera, target = self._trained(grad_threshold=1e9)
        reset = backbone.density_control.schedule.reset_every
        train_step(backbone, optimizer, camera, target, reset - 1)
        with torch.no_grad():
            backbone.opacity_logits.fill_(3.0)
        train_step(backbone, optimizer, camera, target, reset)
        assert torch.sigmoid(backbone.opacity_logits).max() <= 0.0100001
        assert optimizer.state[backbone.opacity_logits]["exp_avg"].abs().max() == 0
        assert_optimizer_consistent(backbone, optimizer)

    def test_schedule_scales_with_run_length(self):
        backbone = GaussianBackbone(GaussianConfig(), make_scene())
        backbone.set_run_length(30_000)
        full = backbone.density_control.schedule
        backbone.set_run_length(3_000)
        short = backbone.density_control.schedule
        assert (full.refine_start, full.refine_stop, full.refine_every, full.reset_every) == (500, 15_000, 100, 3000)
        assert (short.refine_start, short.refine_stop, short.refine_every, short.reset_every) == (50, 1500, 10, 300)


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
        with pytest.raises(Exception):
            load_ply(tmp_path / "junk.ply")
