import math
from importlib.metadata import entry_points

import pytest
import torch

from backbones.nerf import NerfBackbone, NerfConfig
from mono_hdr_plugin.backbone import Backbone, SceneInfo
from mono_hdr_plugin.cameras import Camera
from mono_hdr_plugin.registry import get_backbone

from mono_hdr_plugin.cameras import look_at
from nerf_scenes import orbit_camera, tiny_config

FIELDS = ("paper", "fast")


def filled_fast_backbone(scene) -> NerfBackbone:
    """A fast backbone whose density grid has been filled (occupancy skipping active)."""
    backbone = NerfBackbone(tiny_config("fast"), scene)
    backbone.after_step(0, None, None)
    return backbone


class TestNerfPresets:
    def test_paper_preset_is_the_official_recipe(self):
        config = NerfBackbone.presets()["paper"]
        paper = config.paper
        assert config.field == "paper"
        assert (paper.depth, paper.width, paper.skip_layer) == (8, 256, 4)
        assert (paper.xyz_frequencies, paper.dir_frequencies) == (10, 4)
        assert (paper.coarse_samples, paper.fine_samples, paper.rays_per_step) == (64, 128, 1024)
        assert paper.lr == 5e-4

    def test_fast_is_the_default(self):
        presets = NerfBackbone.presets()
        assert next(iter(presets)) == "fast"
        assert presets["fast"] == NerfConfig()
        assert NerfConfig().background == (0.0, 0.0, 0.0)


class TestNerfBackboneSetup:
    def test_registered_under_nerf(self):
        assert get_backbone("nerf") is NerfBackbone
        assert any(ep.name == "nerf" and ep.load() is NerfBackbone
                   for ep in entry_points(group="mono_hdr.backbones"))

    def test_class_attributes(self, scene):
        assert issubclass(NerfBackbone, Backbone)
        assert NerfBackbone.config_class is NerfConfig and NerfBackbone.loss_kind == "mse"
        backbone = NerfBackbone(tiny_config("paper", render_chunk=123), scene)
        assert backbone.pixel_batch == 64 and backbone.render_chunk == 123

    @pytest.mark.parametrize("bounds", [(torch.ones(3), torch.ones(3)), (torch.zeros(3), torch.tensor([1.0, math.nan, 1.0]))])
    def test_bad_bounds_name_the_argument(self, scene, bounds):
        bad = SceneInfo(bounds_min=bounds[0], bounds_max=bounds[1], train_cameras=scene.train_cameras)
        with pytest.raises(ValueError, match="bounds_min/bounds_max"):
            NerfBackbone(tiny_config("fast"), bad)

    def test_bad_sample_counts_raise(self, scene):
        config = tiny_config("paper")
        config.paper.coarse_samples = 2
        with pytest.raises(ValueError, match="coarse_samples"):
            NerfBackbone(config, scene)

    def test_parameter_groups_cover_every_parameter(self, scene):
        for field in FIELDS:
            backbone = NerfBackbone(tiny_config(field), scene)
            grouped = [p for group in backbone.parameter_groups() for p in group["params"]]
            assert {id(p) for p in grouped} == {id(p) for p in backbone.parameters()}
            assert len(grouped) == len(list(backbone.parameters()))

    def test_learning_rate_schedules(self, scene):
        paper = NerfBackbone(tiny_config("paper"), scene)
        assert paper.learning_rate("nerf_mlp", 0, 5e-4) == 5e-4
        assert paper.learning_rate("nerf_mlp", 250_000, 5e-4) == pytest.approx(5e-5)
        fast = NerfBackbone(tiny_config("fast"), scene)
        fast.set_run_length(1000)
        assert fast.learning_rate("nerf_grid", 1000, 1e-2) == pytest.approx(1e-3)
        assert fast.learning_rate("nerf_grid", 500, 1e-2) == pytest.approx(1e-2 * 0.1 ** 0.5)

    def test_after_step_fills_density_grid_on_schedule(self, scene):
        backbone = NerfBackbone(tiny_config("fast"), scene)
        backbone.after_step(1, None, None)
        assert not backbone.density_grid.filled
        backbone.after_step(0, None, None)
        assert backbone.density_grid.filled


class TestRenderLdrFeatures:
    def test_pixel_batch_shapes_paper(self, scene):
        backbone = NerfBackbone(tiny_config("paper"), scene)
        features = backbone.render_ldr_features(orbit_camera().with_pixels(torch.rand(10, 2) * 8))
        assert features.colors.shape == features.raw_colors.shape == (10, 16, 3)  # 8 coarse + 8 fine
        torch.testing.assert_close(features.colors, torch.sigmoid(features.raw_colors))
        assert features.composite(torch.rand(10, 16, 6)).shape == (10, 6)
        assert features.extras["weights"].shape == features.extras["sample_distances"].shape == (10, 16)
        assert features.extras["depth"].shape == features.extras["alpha"].shape == (10,)
        assert (features.extras["alpha"] <= 1.0 + 1e-6).all()

    def test_pixel_batch_shapes_fast(self, scene):
        backbone = NerfBackbone(tiny_config("fast"), scene)
        features = backbone.render_ldr_features(orbit_camera().with_pixels(torch.rand(10, 2) * 8))
        packed = features.extras["ray_indices"].shape[0]
        assert 0 < packed <= 10 * 16  # 8 uniform + 8 importance per ray, before dropping
        assert features.colors.shape == features.raw_colors.shape == (packed, 3)
        torch.testing.assert_close(features.colors, torch.sigmoid(features.raw_colors))
        assert features.composite(torch.rand(packed, 6)).shape == (10, 6)
        assert features.extras["weights"].shape == features.extras["sample_distances"].shape == (10, 16)
        assert features.extras["depth"].shape == features.extras["alpha"].shape == (10,)
        assert (features.extras["alpha"] <= 1.0 + 1e-6).all()

    @pytest.mark.parametrize("field", FIELDS)
    def test_full_image_shapes(self, scene, field):
        backbone = NerfBackbone(tiny_config(field), scene)
        features = backbone.render_ldr_features(orbit_camera(size=6))
        assert features.extras["weights"].shape[0] == 36
        assert features.composite(features.colors).shape == (6, 6, 3)
        assert features.extras["alpha"].shape == (6, 6)

    def test_paper_has_coarse_auxiliary(self, scene):
        features = NerfBackbone(tiny_config("paper"), scene).render_ldr_features(orbit_camera())
        (coarse,) = features.auxiliary
        assert coarse.colors.shape == (64, 8, 3)
        assert coarse.composite(coarse.colors).shape == (8, 8, 3)

    def test_fast_has_no_auxiliary(self, scene):
        assert NerfBackbone(tiny_config("fast"), scene).render_ldr_features(orbit_camera()).auxiliary == []

    def test_samples_sorted_and_inside_box(self, scene):
        backbone = NerfBackbone(tiny_config("paper"), scene)
        features = backbone.render_ldr_features(orbit_camera())
        t = features.extras["sample_distances"]
        assert (t[:, 1:] >= t[:, :-1]).all()
        _, directions = orbit_camera().rays()
        positions = orbit_camera().center + t[..., None] * directions.reshape(-1, 1, 3)
        hits = t[:, -1] > t[:, 0]  # rays that miss the box have a zero-length segment
        assert hits.sum() > 10
        assert (positions[hits].abs() <= 1.0 + 1e-4).all()

    def test_background_fills_rays_that_miss(self, scene):
        backbone = NerfBackbone(tiny_config("fast", background=(0.1, 0.2, 0.3)), scene)
        looking_away = Camera(look_at(torch.tensor([3.0, 0.0, 0.0]), torch.tensor([6.0, 0.0, 0.0])), 8, 8, 4, 4, 8, 8)
        features = backbone.render_ldr_features(looking_away)
        image = features.composite(torch.rand_like(features.colors))
        torch.testing.assert_close(image, torch.tensor([0.1, 0.2, 0.3]).expand(8, 8, 3))


class TestChunkedRender:
    @pytest.mark.parametrize("field", FIELDS)
    def test_chunks_equal_whole_image(self, scene, field):
        backbone = NerfBackbone(tiny_config(field), scene) if field == "paper" else filled_fast_backbone(scene)
        camera = orbit_camera(size=10)
        with torch.no_grad():
            whole = backbone.render_ldr_features(camera)
            whole_image = whole.composite(whole.colors)
            pixels = camera.pixel_centers()
            parts = []
            for start in range(0, pixels.shape[0], 17):
                part = backbone.render_ldr_features(camera.with_pixels(pixels[start:start + 17]))
                parts.append(part.composite(part.colors))
        torch.testing.assert_close(torch.cat(parts).reshape(10, 10, 3), whole_image)

    def test_training_with_gradients_jitters_samples(self, scene):
        backbone = NerfBackbone(tiny_config("paper"), scene)
        camera = orbit_camera()
        first = backbone.render_ldr_features(camera).extras["sample_distances"]
        second = backbone.render_ldr_features(camera).extras["sample_distances"]
        assert not torch.equal(first, second)


def hard_cameras() -> dict[str, Camera]:
    """Cameras whose rays are parallel to box faces, start inside the box, or have far = near."""
    axis_aligned = torch.eye(4)
    axis_aligned[:3, 3] = torch.tensor([0.0, 0.0, -3.0])  # looks along +z; the central ray is parallel to 4 faces
    inside = torch.eye(4)
    inside[:3, 3] = torch.tensor([0.2, -0.3, 0.1])
    on_face = torch.eye(4)
    on_face[:3, 3] = torch.tensor([1.0, 1.0, -3.0])  # central ray runs along an edge of the box
    return {
        "parallel": Camera(axis_aligned, 4, 4, 2, 2, 4, 4, near=0.5, far=6.0),
        "on_edge": Camera(on_face, 4, 4, 2, 2, 4, 4, near=0.5, far=6.0),
        "inside": Camera(inside, 4, 4, 2, 2, 4, 4, near=0.0, far=6.0),
        "far_equals_near": Camera(axis_aligned, 4, 4, 2, 2, 4, 4, near=3.0, far=3.0),
        "zero_near_far": Camera(inside, 4, 4, 2, 2, 4, 4, near=0.0, far=0.0),
    }


class TestHardRays:
    @pytest.mark.parametrize("field", FIELDS)
    @pytest.mark.parametrize("case", sorted(hard_cameras()))
    def test_finite_values_and_gradients(self, scene, field, case):
        backbone = NerfBackbone(tiny_config(field), scene)
        camera = hard_cameras()[case]
        features = backbone.render_ldr_features(camera)
        image = features.composite(torch.cat([features.colors, features.colors.exp()], -1))
        loss = image.square().mean() + sum(a.composite(a.colors).square().mean() for a in features.auxiliary)
        loss.backward()
        assert torch.isfinite(image).all()
        assert torch.isfinite(features.extras["depth"]).all()
        assert (features.extras["alpha"] <= 1.0 + 1e-6).all()
        assert all(p.grad is None or torch.isfinite(p.grad).all() for p in backbone.parameters())

    @pytest.mark.parametrize("field", FIELDS)
    def test_zero_length_rays_render_empty(self, scene, field):
        backbone = NerfBackbone(tiny_config(field), scene)
        features = backbone.render_ldr_features(hard_cameras()["far_equals_near"])
        assert torch.equal(features.extras["alpha"], torch.zeros(4, 4))


class TestPackedSamples:
    def test_packed_composite_equals_dense_composite(self, scene):
        backbone = filled_fast_backbone(scene)
        backbone.config.fast.min_sample_weight = 0.0
        features = backbone.render_ldr_features(orbit_camera())
        weights = features.extras["weights"]
        dense = torch.zeros(weights.numel(), 3)
        kept = (weights.reshape(-1) > 0).nonzero()[:, 0]
        assert kept.shape[0] == features.colors.shape[0]
        dense[kept] = features.colors
        expected = torch.einsum("ns,nsc->nc", weights, dense.reshape(*weights.shape, 3))
        torch.testing.assert_close(features.composite(features.colors), expected.reshape(8, 8, 3))

    def test_dropped_samples_change_pixels_little(self, scene):
        backbone = filled_fast_backbone(scene)
        backbone.config.fast.min_sample_weight = 0.05
        with torch.no_grad():
            dropped = backbone.render_ldr_features(orbit_camera())
            backbone.config.fast.min_sample_weight = 0.0
            full = backbone.render_ldr_features(orbit_camera())
        assert dropped.colors.shape[0] < full.colors.shape[0]
        difference = full.composite(full.colors.new_ones(full.colors.shape)) - dropped.composite(
            dropped.colors.new_ones(dropped.colors.shape))
        # Each dropped sample had weight < 0.05: a pixel loses at most 16 of them.
        assert (difference >= 0).all() and (difference <= 16 * 0.05).all()


class TestOccupancySkipping:
    def test_empty_cells_are_not_evaluated(self, scene):
        backbone = NerfBackbone(tiny_config("fast"), scene)
        backbone.density_grid.update(lambda p: 5.0 * (p[:, 0] > 0.0).float(), decay=0.9)
        evaluated = []
        backbone.grid_field.density_mlp.register_forward_hook(
            lambda module, inputs, output: evaluated.append(inputs[0].shape[0]))
        features = backbone.render_ldr_features(orbit_camera())
        assert 0 < evaluated[0] < features.extras["sample_distances"].numel()
        assert (features.extras["weights"] == 0).any()

    def test_importance_samples_follow_the_density_grid(self, scene):
        backbone = NerfBackbone(tiny_config("fast"), scene)
        # An opaque slab x > 0.5 faces a camera on the +x axis: along the central ray it spans t in [2, 2.5].
        backbone.density_grid.update(lambda p: 50.0 * (p[:, 0] > 0.5).float(), decay=0.9)
        camera = orbit_camera(eye=(3.0, 0.0, 0.0)).with_pixels(torch.full((1, 2), 4.0))
        with torch.no_grad():
            t = backbone.render_ldr_features(camera).extras["sample_distances"]
        # 8 uniform samples over [2, 4] put about 2 in front of t = 2.7; the importance samples add ~8 more.
        assert (t < 2.7).sum() >= 8
