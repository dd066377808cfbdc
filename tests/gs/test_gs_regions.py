"""Region training (--region-pixels, training.regions): a 3DGS step on a random crop of its view.

Each class checks one operation against an independent reference: the crop camera's render against the
full render cut to the crop, the crop's targets against slices of the view, the densification statistic
against a whole-image step, the cost model against counts made by hand, the real trainer's steps."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from gs_scenes import make_camera, random_gaussians
from helpers import tiny_builtin_scenes

from backbones.gs.model import GaussianBackbone, GaussianConfig
from backbones.gs.rasterizer import render_gaussians
from backbones.gs.sky import EnvironmentMap, background_rows
from backbones.gs.strategy import DefaultStrategy
from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.core.cameras import WORLD_UP
from mono_hdr_plugin.core.validation import FlagError
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import View
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.training.batches import training_batch
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.pyramid import ImagePyramid
from mono_hdr_plugin.training.regions import region_size
from mono_hdr_plugin.training.trainer import Trainer

PARAMETERS = ("means", "quats", "scales", "opacities", "values")
# (left, top, width, height) in make_camera's 40 x 32 image (principal point 0.7, -0.4 px off centre)
INTERIOR = (7, 5, 19, 17)
AT_EDGES = (21, 13, 19, 19)  # touches the right and the bottom edge


def crop_offset(crop_camera, camera) -> tuple[int, int]:
    """(left, top) of a crop camera in `camera`'s image, read from the principal points."""
    left, top = camera.cx - crop_camera.cx, camera.cy - crop_camera.cy
    assert left == pytest.approx(round(left), abs=1e-6) and top == pytest.approx(round(top), abs=1e-6)
    return round(left), round(top)


def gaussians(seed: int = 3) -> dict:
    scene = random_gaussians(300, seed=seed)
    return {name: value.clone().requires_grad_(True) for name, value in scene.items()}


def render(scene: dict, camera, backend: str):
    return render_gaussians(*(scene[name] for name in PARAMETERS), camera, backend=backend)


class TestCropCamera:
    """Camera.crop renders exactly the crop of the full render, values and gradients."""

    @pytest.mark.parametrize("backend", ["kernel", "torch"])
    @pytest.mark.parametrize("box", [INTERIOR, AT_EDGES], ids=["interior", "at-edges"])
    def test_render_and_gradients_are_the_full_ones_cut_to_the_crop(self, backend, box):
        camera = make_camera()
        left, top, width, height = box
        rows, cols = slice(top, top + height), slice(left, left + width)
        weights = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(1))
        full_scene, crop_scene = gaussians(), gaussians()
        full, _, full_projected = render(full_scene, camera, backend)
        crop, _, projected = render(crop_scene, camera.crop(*box), backend)
        assert crop.shape == (height, width, 3) and projected.frame == (40, 32)
        assert set(projected.index.tolist()) < set(full_projected.index.tolist())  # culled to the crop
        assert float(full[rows, cols].detach().std()) > 0.05  # the crop shows Gaussians, not background
        torch.testing.assert_close(crop, full[rows, cols], atol=1e-6, rtol=1e-6)
        (full[rows, cols] * weights).sum().backward()  # a loss that reads only the crop's pixels
        (crop * weights).sum().backward()
        culled = 0
        for name in PARAMETERS:
            expected, got = full_scene[name].grad, crop_scene[name].grad
            torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5, msg=name)
            culled += int((expected.abs().sum(-1) if expected.dim() > 1 else expected.abs()).eq(0).sum())
        assert culled > 0  # some Gaussians cannot touch the crop: they get no gradient either way

    def test_the_crop_sees_the_sky_of_its_pixels(self):
        """The environment map (background rows) along the crop camera's rays: the full image's rows."""
        torch.manual_seed(0)
        environment = EnvironmentMap(WORLD_UP, initial=0.0)
        with torch.no_grad():
            for parameter in environment.parameters():
                parameter.copy_(torch.rand_like(parameter))
        camera = make_camera()
        left, top, width, height = INTERIOR
        full = background_rows(environment, camera).reshape(32, 40, -1)[top : top + height, left : left + width]
        crop = background_rows(environment, camera.crop(*INTERIOR)).reshape(height, width, -1)
        # float32 rays (pixel - cx) round differently; random texels turn that into ~1e-5 of a value
        torch.testing.assert_close(crop, full, atol=1e-4, rtol=0)
        assert float((crop - full).detach().abs().mean()) < 1e-6
        _, full_rays = camera.rays()
        _, crop_rays = camera.crop(*INTERIOR).rays()
        torch.testing.assert_close(crop_rays, full_rays[top : top + height, left : left + width], atol=1e-6, rtol=0)

    def test_a_crop_of_a_crop_keeps_the_whole_frame_and_a_crop_must_fit(self):
        camera = make_camera()
        inner = camera.crop(*INTERIOR).crop(2, 3, 5, 6)
        assert inner.frame_size == (40, 32) and crop_offset(inner, camera) == (9, 8)
        whole = inner.uncropped()
        assert (whole.width, whole.height, whole.frame) == (40, 32, None)
        assert (whole.cx, whole.cy) == pytest.approx((camera.cx, camera.cy), abs=1e-12)
        with pytest.raises(ValueError, match="leaves the 40x32 image"):
            camera.crop(30, 0, 11, 5)


def demo_view(size: int = 64) -> View:
    return load_scene(DataConfig(scene="demo", resolution=size)).train[0]


class TestCropTargets:
    """training_batch with region_pixels: the crop's camera and the same pixels of photo and HDR."""

    @pytest.mark.parametrize("seed", range(5))
    def test_targets_are_the_pixels_of_the_crop(self, seed):
        view = demo_view()
        assert view.hdr is not None
        generator = torch.Generator().manual_seed(seed)
        for budget in (121, 700, 1500):
            camera, targets = training_batch(view, None, True, generator, budget)
            left, top = crop_offset(camera, view.camera)
            width, height = camera.width, camera.height
            assert min(left, top) >= 0 and left + width <= 64 and top + height <= 64
            assert abs(width * height - budget) <= max(width, height) / 2 + 1  # rounding of the sides
            assert abs(width - height) <= 1 and camera.frame_size == (64, 64)
            assert (camera.fx, camera.fy, camera.c2w) == (view.camera.fx, view.camera.fy, view.camera.c2w)
            assert torch.equal(targets.ldr, view.image[top : top + height, left : left + width])
            assert torch.equal(targets.hdr, view.hdr[top : top + height, left : left + width])
            assert targets.exposure == view.exposure

    def test_positions_are_uniform_and_repeatable(self):
        view = demo_view()

        def lefts(seed):
            generator = torch.Generator().manual_seed(seed)
            return [crop_offset(training_batch(view, None, False, generator, 1024)[0], view.camera) for _ in range(400)]

        offsets = np.array(lefts(0))
        assert offsets.min() == 0 and offsets.max() == 64 - 32  # every position, the edges included
        assert offsets.mean(0) == pytest.approx([16, 16], abs=1.5)  # uniform: centred on average
        assert lefts(0) == [tuple(offset) for offset in offsets.tolist()] and lefts(1) != lefts(0)

    def test_an_image_within_the_budget_trains_whole(self):
        view = demo_view(32)
        for budget in (32 * 32, 5000):
            camera, targets = training_batch(view, None, True, torch.Generator(), budget)
            assert camera is view.camera and targets.ldr is view.image and targets.hdr is view.hdr

    def test_a_narrow_image_gets_the_budget_in_the_long_side(self):
        assert region_size(1000, 20, 4096) == (205, 20)
        assert region_size(128, 128, 4096) == (64, 64)
        assert region_size(60, 60, 4096) == (60, 60)


class TestDensificationStatistic:
    """DefaultStrategy's grad2d with a crop: what a whole-image step gives a Gaussian inside the crop."""

    def test_crop_statistic_equals_the_whole_image_one(self):
        camera = make_camera()
        left, top, width, height = INTERIOR
        rows, cols = slice(top, top + height), slice(left, left + width)
        target = torch.rand(32, 40, 3, generator=torch.Generator().manual_seed(2))
        strategy = DefaultStrategy()
        statistics = []
        for crop in (False, True):
            scene = gaussians()
            view_camera = camera.crop(*INTERIOR) if crop else camera
            image, _, projected = render(scene, view_camera, "kernel")
            projected.means2d.retain_grad()
            if crop:  # the step's loss: a mean over the crop's pixels
                loss = (image - target[rows, cols]).abs().mean()
            else:  # the whole image's mean loss, of which only the crop's pixels are kept
                loss = (image[rows, cols] - target[rows, cols]).abs().sum() / (32 * 40 * 3)
            loss.backward()
            state = strategy.initial_state(300)
            model = SimpleNamespace(means=scene["means"])
            strategy.step_post_backward(model, None, state, 0, 30000, projected, budget=10**6)
            statistics.append((state, projected.index))
        (full, _), (cropped, seen) = statistics
        assert seen.numel() > 20 and float(cropped["grad2d_sum"][seen].abs().min()) >= 0
        assert float(cropped["grad2d_sum"][seen].max()) > 1e-4
        torch.testing.assert_close(cropped["grad2d_sum"][seen], full["grad2d_sum"][seen], rtol=1e-3, atol=1e-9)
        assert torch.equal(cropped["visible_count"][seen], torch.ones(seen.numel()))
        # a Gaussian the crop cannot see gathers nothing from it
        unseen = torch.ones(300, dtype=torch.bool)
        unseen[seen] = False
        assert unseen.any() and float(cropped["grad2d_sum"][unseen].abs().max()) == 0


def fake_views(width: int, height: int, count: int = 2) -> list:
    return [SimpleNamespace(camera=SimpleNamespace(width=width, height=height))] * count


class TestCostModel:
    """ImagePyramid.cost with --region-pixels, in full-size steps, against counts made by hand."""

    # 64 x 64 views, 3 levels, half the run coarse: 12 steps are 3 at 16 px, 3 at 32 px, 6 at 64 px
    @pytest.mark.parametrize(
        "region,expected",
        [
            (None, 3 / 16 + 3 / 4 + 6),  # 256, 1024, 4096 px of 4096
            (1024, 3 * 256 / 1024 + 3 + 6),  # 256, 1024, 1024 px of 1024
            (200, 12.0),  # every level renders 200 px (16 x 16 = 256 > 200)
            (4096, 3 / 16 + 3 / 4 + 6),  # the budget holds the whole image: as without regions
            (10**6, 3 / 16 + 3 / 4 + 6),
        ],
    )
    def test_by_hand(self, region, expected):
        pyramid = ImagePyramid(fake_views(64, 64), 3, 0.5, True, region)
        assert [pyramid.level_at(step, 12) for step in range(12)] == [2] * 3 + [1] * 3 + [0] * 6
        assert pyramid.cost(0, 12, 12) == pytest.approx(expected, abs=1e-12)
        assert pyramid.cost(4, 7, 12) == pytest.approx(sum(pyramid.level_costs[level] for level in (1, 1, 0)))

    def test_without_a_pyramid_a_step_is_a_step(self):
        assert ImagePyramid(fake_views(64, 64), 1, 0.5, True, 500).cost(3, 10, 12) == 7.0

    def test_ray_batches_refuse_the_flag(self):
        with pytest.raises(FlagError, match=r"^--region-pixels 500: this backbone trains on random ray batches"):
            ImagePyramid(fake_views(64, 64), 1, 0.5, False, 500)


def make_config(tmp_path, backbone_config, **flags):
    return train_config_for(type(backbone_config))(
        backbone=backbone_config, out=tmp_path / "run", quiet=True, save_renders=False, **flags
    )


def watch_cameras(trainer: Trainer) -> list:
    cameras: list = []
    forward = trainer.pipeline.forward

    def spy(camera, *args, **kwargs):
        cameras.append(camera)
        return forward(camera, *args, **kwargs)

    trainer.pipeline.forward = spy
    return cameras


@pytest.fixture(scope="module")
def scene(studio_cache):
    """The tiny demo scene rendered at 64 px (a module fixture is set up before the autouse one)."""
    with tiny_builtin_scenes():
        return load_scene(DataConfig(scene="demo", resolution=64))


class TestTrainerSteps:
    """--region-pixels through the real Trainer: crops at every level, the pyramid on and off."""

    def test_two_steps_on_crops(self, tmp_path, scene):
        preset = GaussianBackbone.presets()["cpu"]
        config = make_config(tmp_path, preset, max_steps=2, region_pixels=600, pyramid_levels=1)
        trainer = Trainer(config, "gs", scene)
        cameras = watch_cameras(trainer)
        losses = [trainer.train_step()["loss"] for _ in range(2)]
        assert np.isfinite(losses).all()
        assert [(c.width, c.height, c.frame_size) for c in cameras] == [(24, 25, (64, 64))] * 2
        assert trainer.backbone.full_budget == GaussianBackbone(preset, scene.scene_info()).full_budget

    def test_with_the_pyramid_a_small_level_trains_whole(self, tmp_path, scene):
        config = make_config(
            tmp_path, GaussianConfig(), max_steps=6, region_pixels=600, pyramid_levels=3, pyramid_share=4 / 6
        )
        trainer = Trainer(config, "gs", scene)  # the paper recipe: DefaultStrategy's statistic sees crops
        cameras = watch_cameras(trainer)
        records = [trainer.train_step() for _ in range(6)]
        assert np.isfinite([r["loss"] for r in records]).all() and not any(r["skipped"] for r in records)
        sizes = [(c.width, c.height, c.frame and c.frame_size) for c in cameras]
        assert sizes == [(16, 16, None)] * 2 + [(24, 25, (32, 32))] * 2 + [(24, 25, (64, 64))] * 2
        assert trainer.pyramid.level_costs == [1.0, 1.0, 256 / 600]

    def test_a_step_on_a_crop_leaves_the_gaussians_it_did_not_see(self, tmp_path, scene):
        """Adam steps only the rows the crop saw (training.visible_adam): a Gaussian seen by the first
        crop and not the second keeps its colour through the second step, though plain Adam's momentum
        would move it; the rows the optimiser was given are the crop's projected Gaussians."""
        config = make_config(tmp_path, GaussianConfig(), max_steps=2, region_pixels=600, pyramid_levels=1)
        trainer = Trainer(config, "gs", scene)
        cameras = watch_cameras(trainer)
        seen, projected, colours = [], [], []
        step = trainer.optimizer.step

        def spy(rows=None):
            seen.append(rows)
            with torch.no_grad():  # the Gaussians as the step's forward pass saw them
                projected.append(trainer.backbone.render_ldr_features(cameras[-1]).extras["projected"].index)
            step(rows)
            colours.append(trainer.backbone.sh_dc.detach().clone())

        trainer.optimizer.step = spy
        before = trainer.backbone.sh_dc.detach().clone()
        for _ in range(2):
            trainer.train_step()
        assert all(torch.equal(rows, index) for rows, index in zip(seen, projected, strict=True))
        first_only = torch.tensor(sorted(set(seen[0].tolist()) - set(seen[1].tolist())))
        unseen = torch.ones(len(before), dtype=torch.bool)
        unseen[torch.cat(seen)] = False
        assert first_only.numel() > 0 and unseen.any()
        assert torch.equal(colours[1][first_only], colours[0][first_only])
        assert torch.equal(colours[1][unseen], before[unseen])
        assert not torch.equal(colours[1][seen[1]], colours[0][seen[1]])

    @pytest.mark.parametrize("background", ["environment", "sky-gaussians"])
    def test_crops_with_refined_poses_learned_white_balance_and_a_sky(self, tmp_path, scene, background):
        """The paths that take the step's camera: pose refinement (a new c2w, the crop's intrinsics and
        frame kept), per-view exposure and white balance, the environment map or sky Gaussians."""
        from dataclasses import replace

        from mono_hdr_plugin.core.camera_optimizer import CameraOptConfig
        from mono_hdr_plugin.core.exposure import ExposureConfig

        preset = replace(GaussianBackbone.presets()["cpu"], background=background)
        config = make_config(
            tmp_path,
            preset,
            max_steps=2,
            region_pixels=600,
            pyramid_levels=1,
            camera=CameraOptConfig(camera_opt="on"),
            exposure=ExposureConfig(learn_exposure=True, learn_white_balance="on"),
        )
        trainer = Trainer(config, "gs", scene)
        refined: list = []
        refine = trainer.pipeline.poses.refine
        trainer.pipeline.poses.refine = lambda camera, view: refined.append(refine(camera, view)) or refined[-1]
        records = [trainer.train_step() for _ in range(2)]
        assert np.isfinite([r["loss"] for r in records]).all() and not any(r["skipped"] for r in records)
        assert [(c.width, c.height, c.frame_size, c.c2w.requires_grad) for c in refined] == [
            (24, 25, (64, 64), True)
        ] * 2
        # a step that left the pose corrections without a gradient raises (Pipeline.check_pose_gradient)
        assert (trainer.backbone.environment if background == "environment" else trainer.backbone.sky) is not None

    def test_nerf_refuses_the_flag(self, tmp_path, scene):
        from mono_hdr_plugin.core.registry import get_backbone

        preset = next(iter(get_backbone("nerf").presets().values()))
        with pytest.raises(FlagError, match=r"^--region-pixels 600: .*ray batches.*: leave it out$"):
            Trainer(make_config(tmp_path, preset, max_steps=2, region_pixels=600), "nerf", scene)


class TestBadValues:
    @pytest.mark.parametrize("value", ["0", "-5", "120", str(4096**2 + 1), "10000000000000"])
    def test_out_of_range_is_one_line_naming_the_flag(self, value, tmp_path, monkeypatch):
        import mono_hdr_plugin.data.loading as loading

        monkeypatch.chdir(tmp_path)
        monkeypatch.setattr(loading, "load_scene", lambda config: pytest.fail("the data was loaded first"))
        message = rf"^--region-pixels must be an integer in \[121, 16777216\], got {value}$"
        with pytest.raises(FlagError, match=message):
            main(["train", "gs", "--region-pixels", value, "--scene", "demo"])
        assert list(tmp_path.iterdir()) == []

    @pytest.mark.parametrize("value", ["nan", "inf", "1.5"])
    def test_not_an_integer_is_refused_by_the_parser(self, value, tmp_path, monkeypatch, capsys):
        monkeypatch.chdir(tmp_path)
        with pytest.raises(SystemExit) as exit_info:
            main(["train", "gs", "--region-pixels", value, "--scene", "demo"])
        assert exit_info.value.code == 2 and "--region-pixels" in capsys.readouterr().err
        assert list(tmp_path.iterdir()) == []
