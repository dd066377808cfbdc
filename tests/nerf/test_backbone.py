import dataclasses
import math
from importlib.metadata import entry_points

import pytest
import torch
import torch.nn.functional as F
from helpers import quiet_config
from nerf_scenes import orbit_camera, tiny_config

from backbones.nerf import GridFieldConfig, MlpFieldConfig, NerfBackbone, NerfConfig
from backbones.nerf.rendering import compositing_weights
from mono_hdr_plugin.core.backbone import Backbone, SceneInfo
from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.core.registry import get_backbone

FIELDS = ("paper", "cpu")
COLOR_ACTIVATIONS = {"sigmoid": torch.sigmoid, "softplus": F.softplus}


def filled_grid_backbone(scene) -> NerfBackbone:
    """A cpu-field backbone whose occupancy grid has been refreshed once (skipping active)."""
    backbone = NerfBackbone(tiny_config("cpu"), scene)
    backbone.after_step(0, None, None)
    return backbone


class TestNerfPresets:
    def test_paper_preset_is_the_official_recipe(self):
        paper = NerfBackbone.presets()["paper"].field
        assert isinstance(paper, MlpFieldConfig)
        assert (paper.depth, paper.width, paper.skip_layer) == (8, 256, 4)
        assert (paper.xyz_frequencies, paper.dir_frequencies) == (10, 4)
        assert (paper.coarse_samples, paper.fine_samples, paper.rays_per_step) == (64, 128, 1024)
        assert paper.lr == 5e-4

    def test_cpu_is_the_default(self):
        presets = NerfBackbone.presets()
        assert list(presets) == ["cpu", "paper"]
        assert presets["cpu"] == NerfConfig()
        assert isinstance(NerfConfig().field, GridFieldConfig)
        assert NerfConfig().background_color == (0.0, 0.0, 0.0)


class TestNerfBackboneSetup:
    def test_registered_under_nerf(self):
        assert get_backbone("nerf") is NerfBackbone
        assert any(ep.name == "nerf" and ep.load() is NerfBackbone for ep in entry_points(group="mono_hdr.backbones"))

    @pytest.mark.parametrize("preset,builds", [("cpu", 1), ("paper", 0)])
    def test_the_kernels_are_built_at_construction(self, scene, monkeypatch, preset, builds):
        # A first build takes a minute: inside the first step it would count as training time.
        calls = []
        monkeypatch.setattr("backbones.nerf.backbone.load_extension", lambda: calls.append(1))
        NerfBackbone(tiny_config(preset), scene)
        assert len(calls) == builds

    def test_class_attributes(self, scene):
        assert issubclass(NerfBackbone, Backbone)
        assert NerfBackbone.config_class is NerfConfig and NerfBackbone.loss_kind == "mse"
        backbone = NerfBackbone(tiny_config("paper", render_chunk=123), scene)
        assert backbone.pixel_batch == 64 and backbone.render_chunk == 123

    @pytest.mark.parametrize(
        "bounds", [(torch.ones(3), torch.ones(3)), (torch.zeros(3), torch.tensor([1.0, math.nan, 1.0]))]
    )
    def test_bad_bounds_name_the_argument(self, scene, bounds):
        bad = SceneInfo(bounds_min=bounds[0], bounds_max=bounds[1], train_cameras=scene.train_cameras)
        with pytest.raises(ValueError, match="bounds_min/bounds_max"):
            NerfBackbone(tiny_config("cpu"), bad)

    @pytest.mark.parametrize(
        "field,name,value",
        [("paper", "coarse_samples", 2), ("cpu", "max_samples_per_ray", 0), ("cpu", "min_step", 0.0)],
    )
    def test_bad_sample_settings_raise(self, scene, field, name, value):
        config = tiny_config(field)
        setattr(config.field, name, value)
        with pytest.raises(ValueError, match=name):
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
        grid = NerfBackbone(tiny_config("cpu"), scene)
        grid.set_run_length(1000)
        assert grid.learning_rate("nerf_grid", 0, 1e-2) == pytest.approx(1e-2)
        assert grid.learning_rate("nerf_grid", 1000, 1e-2) == pytest.approx(1e-3)
        assert grid.learning_rate("nerf_grid", 500, 1e-2) == pytest.approx(1e-2 * 0.1**0.5)

    def test_a_new_run_length_rescales_the_schedule_and_keeps_the_model(self, scene):
        """--max-seconds tells the backbone a new run length while it trains."""
        backbone = filled_grid_backbone(scene)
        backbone.set_run_length(1000)
        before = {name: value.clone() for name, value in backbone.state_dict().items()}
        backbone.set_run_length(2000)
        assert backbone.learning_rate("nerf_grid", 500, 1e-2) == pytest.approx(1e-2 * 0.1**0.25)
        assert backbone.learning_rate("nerf_mlp", 2000, 1e-2) == pytest.approx(1e-3)
        backbone.set_run_length(400)  # shorter than the steps already taken: stays at the final rate
        assert backbone.learning_rate("nerf_grid", 500, 1e-2) == pytest.approx(1e-3)
        after = backbone.state_dict()
        assert before.keys() == after.keys()
        assert all(torch.equal(before[name], after[name]) for name in before)

    def test_after_step_refreshes_occupancy_on_schedule(self, scene):
        backbone = NerfBackbone(tiny_config("cpu"), scene)
        backbone.after_step(1, None, None)
        assert not backbone.occupancy.filled
        backbone.after_step(0, None, None)
        assert backbone.occupancy.filled

    def test_cells_no_camera_sees_are_never_occupied(self):
        # One camera far out on +x with a narrow view (half a unit wide at the origin): the box's corners are unseen.
        camera = Camera(
            look_at(torch.tensor([10.0, 0.0, 0.0]), torch.zeros(3)), 160, 160, 4, 4, 8, 8, near=0.5, far=20.0
        )
        scene = SceneInfo(bounds_min=-torch.ones(3), bounds_max=torch.ones(3), train_cameras=[camera])
        backbone = NerfBackbone(tiny_config("cpu"), scene)
        occupancy = backbone.occupancy
        assert 0 < occupancy.seen.sum() < occupancy.seen.numel()
        assert occupancy.seen[4, 4, 4] and not occupancy.seen[0, 0, 0] and not occupancy.seen[7, 7, 7]
        backbone.occupancy.update(lambda p: torch.full(p.shape[:1], 100.0), decay=0.9, threshold=1.0)
        assert torch.equal(occupancy.occupied, occupancy.seen)

    def test_statistics_count_occupied_seen_cells(self, scene):
        backbone = NerfBackbone(tiny_config("cpu"), scene)
        assert backbone.statistics() == {"occupied_fraction": 1.0}
        # Dense only where x > 0 (a cell border at an even resolution): exactly the cells right of it.
        backbone.occupancy.update(lambda p: torch.where(p[:, 0] > 0, 100.0, 0.0), decay=0.9, threshold=1.0)
        right = (backbone.occupancy.cell_centers()[:, 0] > 0).reshape(backbone.occupancy.seen.shape)
        seen = backbone.occupancy.seen
        expected = float((right & seen).sum()) / float(seen.sum())
        assert 0 < expected < 1 and backbone.statistics()["occupied_fraction"] == pytest.approx(expected)
        assert NerfBackbone(tiny_config("paper"), scene).statistics() == {}


class TestRenderLdrFeatures:
    def test_pixel_batch_shapes_paper(self, scene):
        backbone = NerfBackbone(tiny_config("paper"), scene)
        features = backbone.render_ldr_features(orbit_camera().with_pixels(torch.rand(10, 2) * 8))
        assert features.colors.shape == features.raw_colors.shape == (10, 16, 3)  # 8 coarse + 8 fine
        torch.testing.assert_close(features.colors, torch.sigmoid(features.raw_colors))
        assert features.l2h_inputs is None  # the paper's field: L2H-CC reads the LDR colours
        assert features.composite(torch.rand(10, 16, 6)).shape == (10, 6)
        assert features.extras["weights"].shape == features.extras["sample_distances"].shape == (10, 16)
        assert features.extras["depth"].shape == features.extras["alpha"].shape == (10,)
        assert (features.extras["alpha"] <= 1.0 + 1e-6).all()

    @pytest.mark.parametrize("importance,columns", [(0, 16), (4, 4)])
    @pytest.mark.parametrize("activation", ["sigmoid", "softplus"])
    def test_pixel_batch_shapes_cpu(self, scene, importance, columns, activation):
        """importance 0: the marched samples (max_samples_per_ray columns); else importance_samples per ray."""
        backbone = NerfBackbone(tiny_config("cpu"), scene)
        backbone.config.field.importance_samples = importance
        backbone.config.field.color_activation = activation
        features = backbone.render_ldr_features(orbit_camera().with_pixels(torch.rand(10, 2) * 8))
        packed = features.extras["ray_indices"].shape[0]
        assert 0 < packed <= 10 * columns
        assert features.colors.shape == features.raw_colors.shape == (packed, 3)
        torch.testing.assert_close(features.colors, COLOR_ACTIVATIONS[activation](features.raw_colors))
        assert features.l2h_inputs is features.raw_colors  # the default l2h_input, "raw"
        assert features.composite(torch.rand(packed, 6)).shape == (10, 6)
        assert features.extras["weights"].shape == features.extras["sample_distances"].shape == (10, columns)
        assert features.extras["depth"].shape == features.extras["alpha"].shape == (10,)
        assert (features.extras["alpha"] <= 1.0 + 1e-6).all()

    def test_l2h_reads_the_activated_colours_when_asked(self, scene):
        backbone = NerfBackbone(tiny_config("cpu"), scene)
        backbone.config.field.l2h_input = "activated"
        assert backbone.render_ldr_features(orbit_camera().with_pixels(torch.rand(10, 2) * 8)).l2h_inputs is None

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

    def test_cpu_has_no_auxiliary(self, scene):
        assert NerfBackbone(tiny_config("cpu"), scene).render_ldr_features(orbit_camera()).auxiliary == []

    @pytest.mark.parametrize("field", FIELDS)
    def test_samples_sorted_and_inside_box(self, scene, field):
        backbone = NerfBackbone(tiny_config(field), scene)
        features = backbone.render_ldr_features(orbit_camera())
        t = features.extras["sample_distances"]
        assert (t[:, 1:] >= t[:, :-1]).all()
        _, directions = orbit_camera().rays()
        positions = orbit_camera().center + t[..., None] * directions.reshape(-1, 1, 3)
        hits = t[:, -1] > t[:, 0]  # rays that miss the box have a zero-length segment
        assert hits.sum() > 10
        assert (positions[hits].abs() <= 1.0 + 1e-4).all()

    def test_background_fills_rays_that_miss(self, scene):
        backbone = NerfBackbone(tiny_config("cpu", background_color=(0.1, 0.2, 0.3)), scene)
        looking_away = Camera(look_at(torch.tensor([3.0, 0.0, 0.0]), torch.tensor([6.0, 0.0, 0.0])), 8, 8, 4, 4, 8, 8)
        features = backbone.render_ldr_features(looking_away)
        image = features.composite(torch.rand_like(features.colors))
        torch.testing.assert_close(image, torch.tensor([0.1, 0.2, 0.3]).expand(8, 8, 3))


class TestChunkedRender:
    @pytest.mark.parametrize("field", FIELDS)
    def test_chunks_equal_whole_image(self, scene, field):
        backbone = NerfBackbone(tiny_config(field), scene) if field == "paper" else filled_grid_backbone(scene)
        camera = orbit_camera(size=10)
        with torch.no_grad():
            whole = backbone.render_ldr_features(camera)
            whole_image = whole.composite(whole.colors)
            pixels = camera.pixel_centers()
            parts = []
            for start in range(0, pixels.shape[0], 17):
                part = backbone.render_ldr_features(camera.with_pixels(pixels[start : start + 17]))
                parts.append(part.composite(part.colors))
        torch.testing.assert_close(torch.cat(parts).reshape(10, 10, 3), whole_image)

    @pytest.mark.parametrize("field", FIELDS)
    def test_training_with_gradients_jitters_samples(self, scene, field):
        backbone = NerfBackbone(tiny_config(field), scene)
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


def unpacked_render(backbone: NerfBackbone, camera: Camera) -> torch.Tensor:
    """The cpu field rendered the plain way at the same samples: density and colour at every
    placed sample, dense [rays, samples] compositing, no weight threshold."""
    origins, directions = (x.reshape(-1, 3) for x in camera.rays())
    t, delta, flat = backbone.place_samples(origins, directions, camera, stochastic=False)
    positions = backbone.normalise(origins[:, None] + t[..., None] * directions[:, None])
    placed = torch.zeros(t.numel(), dtype=torch.bool)
    placed[flat] = True
    density, raw_color = backbone.grid_field(
        positions.reshape(-1, 3), directions[:, None].expand_as(positions).reshape(-1, 3)
    )
    density = torch.where(placed, density, torch.zeros_like(density)).reshape(t.shape)
    weights = compositing_weights(density, delta)
    colors = COLOR_ACTIVATIONS[backbone.config.field.color_activation](raw_color)
    image = torch.einsum("ns,nsc->nc", weights, colors.reshape(*t.shape, 3))
    return image.reshape(camera.height, camera.width, 3)


def opaque_ball_backbone(scene) -> NerfBackbone:
    """A cpu-field backbone whose density MLP makes an opaque ball of radius 0.5 (normalised)
    in front of random colours, with the occupancy grid refreshed from it."""
    backbone = NerfBackbone(tiny_config("cpu"), scene)
    field = backbone.grid_field
    original = field.density_and_geometry

    def ball(positions):
        density, geometry = original(positions)
        return density + 200.0 * (positions.norm(dim=-1) < 0.5).float(), geometry

    field.density_and_geometry = ball
    backbone.refresh_occupancy()
    return backbone


class TestPackedSamples:
    @pytest.mark.parametrize("min_weight,tolerance", [(0.0, 1e-5), (1e-4, 16 * 1e-4)])
    def test_packed_and_unpacked_render_the_same_image(self, scene, min_weight, tolerance):
        backbone = opaque_ball_backbone(scene)
        backbone.config.field.min_sample_weight = min_weight
        camera = orbit_camera(size=12)
        with torch.no_grad():
            features = backbone.render_ldr_features(camera)
            packed = features.composite(features.colors)
            reference = unpacked_render(backbone, camera)
        assert reference.amax() > 0.2  # the ball is in view
        # A dropped sample has weight < min_weight: a pixel loses at most 16 (samples per ray) of them.
        torch.testing.assert_close(packed, reference, atol=tolerance, rtol=0)

    def test_early_stop_while_training_changes_pixels_by_at_most_its_threshold(self, scene):
        backbone = opaque_ball_backbone(scene)
        evaluated = []
        backbone.grid_field.density_mlp.register_forward_hook(
            lambda module, inputs, output: evaluated.append((torch.is_grad_enabled(), inputs[0].shape[0]))
        )
        camera = orbit_camera(size=12)
        torch.manual_seed(3)
        stopped = backbone.render_ldr_features(camera)
        backbone.config.field.early_stop_transmittance = 0.0
        torch.manual_seed(3)
        full = backbone.render_ldr_features(camera)
        (first_pass, with_grad, unstopped) = evaluated
        assert not first_pass[0] and with_grad[0] and unstopped[0]
        assert with_grad[1] < first_pass[1] == unstopped[1]  # samples behind the ball got no gradient pass
        ones = lambda f: f.composite(torch.ones_like(f.colors))  # noqa: E731 - the opacity, as a one-liner
        torch.testing.assert_close(ones(stopped), ones(full), atol=1e-4 + 16 * 1e-4, rtol=0)

    def test_weight_threshold_drops_only_light_samples(self, scene):
        backbone = filled_grid_backbone(scene)
        backbone.config.field.min_sample_weight = 0.05
        with torch.no_grad():
            dropped = backbone.render_ldr_features(orbit_camera())
            backbone.config.field.min_sample_weight = 0.0
            full = backbone.render_ldr_features(orbit_camera())
        assert dropped.colors.shape[0] < full.colors.shape[0]
        difference = full.composite(full.colors.new_ones(full.colors.shape)) - dropped.composite(
            dropped.colors.new_ones(dropped.colors.shape)
        )
        # Each dropped sample had weight < 0.05: a pixel loses at most 16 of them.
        assert (difference >= 0).all() and (difference <= 16 * 0.05).all()


class TestOccupancySkipping:
    def test_empty_cells_are_not_evaluated(self, scene):
        backbone = NerfBackbone(tiny_config("cpu"), scene)
        backbone.occupancy.update(lambda p: 5.0 * (p[:, 0] > 0.0).float(), decay=0.9, threshold=1.0)
        evaluated = []
        backbone.grid_field.density_mlp.register_forward_hook(
            lambda module, inputs, output: evaluated.append(inputs[0].shape[0])
        )
        with torch.no_grad():
            features = backbone.render_ldr_features(orbit_camera())
        positions = features.extras["sample_distances"]
        assert evaluated[0] > 0
        # Half the cube is empty: every marched sample lies in the x > 0 half.
        origins, directions = (x.reshape(-1, 3) for x in orbit_camera().rays())
        t, _, flat, _ = backbone.march(origins, directions, orbit_camera(), stochastic=False)
        points = backbone.normalise(origins[:, None] + t[..., None] * directions[:, None]).reshape(-1, 3)[flat]
        assert evaluated[0] == flat.numel() and (points[:, 0] > -1e-5).all()
        assert positions.shape == t.shape

    def test_samples_crowd_into_occupied_cells(self, scene):
        backbone = NerfBackbone(tiny_config("cpu"), scene)
        # An occupied slab x > 0.5 faces a camera on the +x axis: along the central ray it spans t in [2, 2.5].
        backbone.occupancy.update(lambda p: 50.0 * (p[:, 0] > 0.5).float(), decay=0.9, threshold=1.0)
        camera = orbit_camera(eye=(3.0, 0.0, 0.0)).with_pixels(torch.full((1, 2), 4.0))
        origins, directions = (x.reshape(-1, 3) for x in camera.rays())
        t, delta, flat, _ = backbone.march(origins, directions, camera, stochastic=False)
        # Occupied length 0.5 at min_step 0.25: 2 samples, both in the slab.
        assert flat.numel() == 2
        torch.testing.assert_close(t[0, :2], torch.tensor([2.125, 2.375]))
        torch.testing.assert_close(delta[0, :2], torch.tensor([0.25, 0.25]))

    def test_refresh_keeps_every_weighted_sample_of_a_trained_field(self, tmp_path, voxel_scene):
        """The occupancy grid of a trained field never drops a sample that carries weight (1 % of its
        ray) in a dense-sampling reference render (every cell occupied, steps 16x finer)."""
        from mono_hdr_plugin.training.trainer import Trainer

        config = NerfConfig(
            field=GridFieldConfig(
                levels=2,
                min_resolution=4,
                max_resolution=16,
                hidden_width=16,
                min_step=1 / 32,
                occupancy_resolution=16,
                occupancy_update_every=4,
                rays_per_step=256,
            )
        )
        train = quiet_config(config, tmp_path, max_steps=150)
        trainer = Trainer(train, "nerf", voxel_scene)
        while trainer.step < train.max_steps:
            trainer.train_step()
        backbone = trainer.backbone.eval()
        occupancy = backbone.occupancy
        assert 0 < occupancy.occupied.sum() < occupancy.seen.sum()  # it does skip space
        # Dense reference: every cell occupied, steps 16x finer, every marched sample shaded.
        dense_field = dataclasses.replace(
            config.field, max_samples_per_ray=256, min_step=config.field.min_step / 16, importance_samples=0
        )
        dense = NerfBackbone(dataclasses.replace(config, field=dense_field), voxel_scene.scene_info())
        dense.load_state_dict(backbone.state_dict())
        dense.occupancy.occupied.fill_(True)
        dense.eval()
        for view in voxel_scene.test:
            with torch.no_grad():
                features = dense.render_ldr_features(view.camera)
            origins, directions = (x.reshape(-1, 3) for x in view.camera.rays())
            weights, t = features.extras["weights"], features.extras["sample_distances"]
            carrying = weights > 1e-2
            points = backbone.normalise(origins[:, None] + t[..., None] * directions[:, None])[carrying]
            cells = ((points + 1) * occupancy.resolution / 2).floor().long().clamp(0, occupancy.resolution - 1)
            assert carrying.sum() > 10
            assert occupancy.occupied[cells[:, 2], cells[:, 1], cells[:, 0]].all()


class TestRenderMemoryBound:
    def test_every_field_call_of_a_full_render_is_bounded_by_the_chunk(self, scene):
        """Memory per piece is bounded by construction: Pipeline.render hands the backbone at most
        render_chunk rays, and the field sees at most render_chunk x max_samples_per_ray samples."""
        from mono_hdr_plugin.methods.base import MethodConfig
        from mono_hdr_plugin.training.pipeline import Pipeline

        pipeline = Pipeline.create("nerf", tiny_config("cpu", render_chunk=50), MethodConfig(), scene).eval()
        backbone = pipeline.backbone
        rays, samples = [], []
        render = backbone.render_ldr_features
        backbone.render_ldr_features = lambda camera: rays.append(camera.pixels.shape[0]) or render(camera)
        backbone.grid_field.density_mlp.register_forward_hook(
            lambda module, inputs, output: samples.append(inputs[0].shape[0])
        )
        output = pipeline.render(orbit_camera(size=30), 1.0)
        assert output.ldr.shape == (30, 30, 3)
        assert sum(rays) == 900 and max(rays) <= 50
        assert len(samples) == len(rays) and max(samples) <= 50 * backbone.config.field.max_samples_per_ray
