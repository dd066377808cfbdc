"""Camera pose refinement (--camera-opt): the exponential map, the corrections, when it is on, training
with it on every backbone, checkpoints and the refined-poses file."""

import dataclasses
import json
import math

import pytest
import register_backbone  # examples/, put on sys.path by conftest
import torch
from helpers import quiet_config

from backbones.gs import GaussianConfig
from backbones.nerf import GridFieldConfig, NerfConfig
from mono_hdr_plugin.core.camera_optimizer import (
    EXACT,
    STRUCTURE_FROM_MOTION,
    CameraOptConfig,
    PoseCorrections,
    pose_exp,
    refinement_wanted,
    rotation_angle_degrees,
    so3_exp,
)
from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.core.metrics import psnr
from mono_hdr_plugin.core.validation import FlagError
from mono_hdr_plugin.training import appearance
from mono_hdr_plugin.training.appearance import APPEARANCE_PROTOCOL, fit_held_out_pose
from mono_hdr_plugin.training.checkpoints import load_checkpoint
from mono_hdr_plugin.training.evaluation import POSE_PROTOCOL, pose_fit_runs
from mono_hdr_plugin.training.hdr_prior import camera_response
from mono_hdr_plugin.training.poses import write_refined_poses
from mono_hdr_plugin.training.resume import ResumeMismatch
from mono_hdr_plugin.training.trained import load_trained_model
from mono_hdr_plugin.training.trainer import Trainer

ON = CameraOptConfig(camera_opt="on")


def rodrigues(axis_angle: torch.Tensor) -> torch.Tensor:
    """Independent reference: R = cos t I + sin t [k]x + (1 - cos t) k k^T for unit axis k, angle t."""
    angle = float(axis_angle.norm())
    k = axis_angle / angle
    cross = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64)
    return math.cos(angle) * eye + math.sin(angle) * cross + (1 - math.cos(angle)) * torch.outer(k, k)


def twist_matrix(tangent: torch.Tensor) -> torch.Tensor:
    """The 4 x 4 Lie-algebra matrix of (translation, rotation), whose matrix exponential is the SE(3) motion."""
    rho, w = tangent[:3], tangent[3:]
    matrix = torch.zeros(4, 4, dtype=torch.float64)
    matrix[:3, :3] = torch.tensor([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]], dtype=torch.float64)
    matrix[:3, 3] = rho
    return matrix


class TestPoseExp:
    @pytest.mark.parametrize("mode", ["SO3xR3", "SE3"])
    def test_zero_is_the_identity(self, mode):
        assert torch.equal(pose_exp(torch.zeros(6), mode), torch.eye(4))

    @pytest.mark.parametrize("angle", [1e-6, 1e-3, 0.3, 2.5])
    def test_rotation_is_rodrigues_formula(self, angle):
        axis_angle = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
        axis_angle = axis_angle / axis_angle.norm() * angle
        torch.testing.assert_close(so3_exp(axis_angle), rodrigues(axis_angle), atol=1e-12, rtol=0)

    def test_so3xr3_keeps_the_translation_as_given(self):
        tangent = torch.tensor([0.2, -0.1, 0.4, 0.3, 0.1, -0.2], dtype=torch.float64)
        motion = pose_exp(tangent, "SO3xR3")
        torch.testing.assert_close(motion[:3, 3], tangent[:3])
        torch.testing.assert_close(motion[:3, :3], rodrigues(tangent[3:]))

    @pytest.mark.parametrize("scale", [1e-6, 0.5, 2.0])
    def test_se3_is_the_matrix_exponential_of_the_twist(self, scale):
        tangent = torch.tensor([0.2, -0.1, 0.4, 0.3, 0.1, -0.2], dtype=torch.float64) * scale
        torch.testing.assert_close(
            pose_exp(tangent, "SE3"), torch.linalg.matrix_exp(twist_matrix(tangent)), atol=1e-12, rtol=0
        )

    def test_gradient_at_zero_is_the_generators(self):
        """d exp / d rotation_x at 0 is [e_x]x: finite, and with the sign that rotates y toward z."""
        tangent = torch.zeros(6, dtype=torch.float64, requires_grad=True)
        jacobian = torch.autograd.functional.jacobian(lambda t: pose_exp(t, "SE3"), tangent)
        assert torch.isfinite(jacobian).all()
        torch.testing.assert_close(jacobian[:3, :3, 3], torch.tensor([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]]).double())
        torch.testing.assert_close(jacobian[:3, 3, 0], torch.tensor([1.0, 0, 0]).double())


class TestRotationAngle:
    def test_identity(self):
        assert rotation_angle_degrees(torch.eye(3)) == 0.0

    @pytest.mark.parametrize("degrees", [1e-4, 0.05, 0.2, 37.0, 179.0])
    def test_angle_of_a_rotation_about_any_axis(self, degrees):
        axis = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
        rotation = rodrigues(axis / axis.norm() * math.radians(degrees))
        assert rotation_angle_degrees(rotation) == pytest.approx(degrees, abs=1e-9)

    def test_small_angles_survive_float32(self):
        """arccos of the trace alone rounds a float32 rotation below about 0.02 degrees to 0."""
        rotation = rodrigues(torch.tensor([0.0, 0.0, math.radians(0.005)], dtype=torch.float64)).float()
        assert rotation_angle_degrees(rotation) == pytest.approx(0.005, rel=1e-3)


class TestPoseCorrections:
    def test_corrects_the_pose_in_the_camera_frame(self):
        """c2w_refined = c2w @ exp(correction): a translation along the camera's own z moves it forward."""
        camera = Camera(look_at(torch.tensor([0.0, -3.0, 0.0]), torch.zeros(3)), 10, 10, 5, 5, 10, 10)
        poses = PoseCorrections(views=2, scene_scale=2.0)
        with torch.no_grad():
            poses.corrections[1][2] = 0.25  # a quarter of the scene radius forward
        refined = poses.refine(camera, 1)
        torch.testing.assert_close(refined.center, torch.tensor([0.0, -2.5, 0.0]))
        assert torch.equal(poses.refine(camera, 0).c2w, camera.c2w)
        assert refined.c2w.requires_grad

    def test_one_tensor_per_view(self):
        """Adam skips a tensor without a gradient: one per view leaves the views a step did not see alone."""
        poses = PoseCorrections(views=3, scene_scale=1.0)
        assert [tuple(p.shape) for p in poses.parameter_groups()[0]["params"]] == [(6,)] * 3


class TestAutoDefault:
    @pytest.mark.parametrize(
        "setting,poses,expected",
        [
            ("auto", STRUCTURE_FROM_MOTION, True),
            ("auto", EXACT, False),
            ("auto", None, False),  # an in-memory scene says nothing: its poses are taken as exact
            ("on", EXACT, True),
            ("off", STRUCTURE_FROM_MOTION, False),
        ],
    )
    def test_decision(self, setting, poses, expected):
        assert refinement_wanted(CameraOptConfig(camera_opt=setting), poses, True, "gs") is expected

    def test_a_backbone_without_pose_gradients_is_left_alone_or_refused(self):
        assert not refinement_wanted(CameraOptConfig(), STRUCTURE_FROM_MOTION, False, "mine")
        with pytest.raises(FlagError, match="differentiable_pose"):
            refinement_wanted(ON, EXACT, False, "mine")

    def test_off_for_a_builtin_scene(self, tmp_path):
        from mono_hdr_plugin.data.config import DataConfig
        from mono_hdr_plugin.data.loading import load_scene

        scene = load_scene(DataConfig(scene="demo"))
        assert scene.metadata["poses"] == EXACT
        config = quiet_config(GaussianConfig(random_init_points=200), tmp_path / "run", max_steps=2)
        assert Trainer(config, "gs", scene).pipeline.poses is None

    @pytest.mark.parametrize("layout", ["hdr-gs", "hdr-nerf-real", "llff", "nerfstudio"])
    def test_on_for_a_structure_from_motion_folder_off_for_one_the_studio_wrote(self, tmp_path, layout):
        """process-data writes the hdr-gs layout (COLMAP) without pose_source.json: its poses are SfM's.
        `mono-hdr synth` marks its exact poses, so a studio scene read back from disk stays unrefined."""
        from mono_hdr_plugin.apps.studio.dataset import get_scene, studio_captured_scene
        from mono_hdr_plugin.data.config import DataConfig
        from mono_hdr_plugin.data.layouts import write_layout
        from mono_hdr_plugin.data.layouts.common import POSE_SOURCE_FILE
        from mono_hdr_plugin.data.loading import load_scene

        folder = tmp_path / "data"
        write_layout(studio_captured_scene(get_scene("demo")), folder, layout)
        config = quiet_config(
            GaussianConfig(random_init_points=200),
            tmp_path / "run",
            max_steps=2,
            camera=CameraOptConfig(camera_opt="auto"),
        )
        config.data = DataConfig(data=folder)
        assert Trainer(config, "gs", load_scene(config.data)).pipeline.poses is None
        (folder / POSE_SOURCE_FILE).unlink()
        scene = load_scene(config.data)
        assert scene.metadata["poses"] == STRUCTURE_FROM_MOTION
        assert len(Trainer(config, "gs", scene).pipeline.poses) == len(scene.train)


def tiny_nerf() -> NerfConfig:
    return NerfConfig(
        field=GridFieldConfig(
            levels=2,
            min_resolution=4,
            max_resolution=8,
            hidden_width=16,
            min_step=0.25,
            max_samples_per_ray=16,
            occupancy_resolution=8,
            rays_per_step=64,
            importance_samples=0,
        )
    )


BACKBONES = {
    "gs": lambda: GaussianConfig(random_init_points=500),
    "nerf": tiny_nerf,
    "voxel-grid": lambda: register_backbone.VoxelGridConfig(resolution=12, samples_per_ray=24),
}


def refining_trainer(tmp_path, scene, backbone: str, **settings) -> Trainer:
    config = quiet_config(BACKBONES[backbone](), tmp_path / "run", camera=ON, **({"max_steps": 2} | settings))
    return Trainer(config, backbone, scene)


class TestTrainingWithRefinement:
    @pytest.mark.parametrize("backbone", ["gs", "nerf", "voxel-grid"])
    def test_two_steps_move_the_poses_of_the_views_trained(self, tmp_path, voxel_scene, backbone):
        """voxel-grid is a backbone registered from examples/: it builds rays with camera.rays() and
        gets refinement without a line of its own."""
        trainer = refining_trainer(tmp_path, voxel_scene, backbone)
        trained: list[int] = []
        next_view = trainer._next_view
        trainer._next_view = lambda: trained.append(next_view()) or trained[-1]
        records = [trainer.train_step() for _ in range(2)]
        assert all(math.isfinite(r["loss"]) and not r["skipped"] for r in records)
        corrections = [p.detach() for p in trainer.pipeline.poses.corrections]
        assert all(torch.isfinite(c).all() for c in corrections)
        moved = {i for i, c in enumerate(corrections) if c.abs().max() > 0}
        assert moved == set(trained)  # the views of the two steps, and no other
        # the translation too: the samples must move with the ray (NeRF's grid kernel differentiated the table only)
        assert all(corrections[i][:3].abs().min() > 0 and corrections[i][3:].abs().min() > 0 for i in moved)

    def test_the_gradient_reaches_the_pose_of_a_3dgs_view(self, tmp_path, voxel_scene):
        trainer = refining_trainer(tmp_path, voxel_scene, "gs")
        trainer.optimizer.step = lambda *args, **kwargs: None  # keep the gradients readable
        trainer.optimizer.zero_grad = lambda *args, **kwargs: None
        trainer.train_step()
        gradients = [p.grad for p in trainer.pipeline.poses.corrections if p.grad is not None]
        assert len(gradients) == 1 and gradients[0].abs().sum() > 0

    def test_held_out_renders_use_the_poses_as_given(self, tmp_path, voxel_scene):
        trainer = refining_trainer(tmp_path, voxel_scene, "voxel-grid")
        with torch.no_grad():
            trainer.pipeline.poses.corrections[0].fill_(0.05)
        view = voxel_scene.train[0]
        with trainer.pipeline.evaluating():
            as_given = trainer.pipeline.render(view.camera, view.exposure).ldr
            trainer.pipeline.poses = None
            unrefined = trainer.pipeline.render(view.camera, view.exposure).ldr
        assert torch.equal(as_given, unrefined)

    def test_a_backbone_that_gives_no_pose_gradient_is_named(self, tmp_path, voxel_scene, monkeypatch):
        trainer = refining_trainer(tmp_path, voxel_scene, "voxel-grid")
        render = trainer.backbone.render_ldr_features
        monkeypatch.setattr(
            trainer.backbone,
            "render_ldr_features",
            lambda camera: render(dataclasses.replace(camera, c2w=camera.c2w.detach())),
        )
        with pytest.raises(RuntimeError, match="no gradient to the camera pose"):
            trainer.train_step()


class TestGridEncodePositionGradient:
    def test_matches_finite_differences(self):
        """The NeRF grid field's C++ encoding is trilinear: its position gradient (taken from the torch
        twin) must match central differences away from cell boundaries."""
        from backbones.nerf.kernels import grid_encode

        generator = torch.Generator().manual_seed(0)
        resolutions, offsets = torch.tensor([4, 8]), torch.tensor([0, 64])
        table = torch.randn(64 + 512, 2, generator=generator)
        positions = (torch.rand(40, 3, generator=generator) * 1.6 - 0.8).requires_grad_()
        weights = torch.randn(40, 4, generator=generator)
        (analytic,) = torch.autograd.grad(
            (grid_encode(positions, table, resolutions, offsets) * weights).sum(), positions
        )
        step, forward, backward = 1e-3, torch.zeros(40, 3), torch.zeros(40, 3)
        with torch.no_grad():
            centre = (grid_encode(positions, table, resolutions, offsets) * weights).sum(-1)
            for axis in range(3):
                offset = torch.zeros(3)
                offset[axis] = step
                plus = (grid_encode(positions + offset, table, resolutions, offsets) * weights).sum(-1)
                minus = (grid_encode(positions - offset, table, resolutions, offsets) * weights).sum(-1)
                forward[:, axis], backward[:, axis] = (plus - centre) / step, (centre - minus) / step
        smooth = (forward - backward).abs() < 1e-2  # no cell boundary within the step
        assert analytic.abs().max() > 0.1 and smooth.float().mean() > 0.9
        torch.testing.assert_close(analytic[smooth], forward[smooth], atol=2e-2, rtol=1e-2)


class TestCheckpointRoundTrip:
    def test_resume_and_load_keep_the_refined_poses(self, tmp_path, voxel_scene):
        trainer = refining_trainer(tmp_path, voxel_scene, "gs", max_steps=3)
        trainer.fit()
        trainer.save()
        saved = [p.detach().clone() for p in trainer.pipeline.poses.corrections]
        assert any(s.abs().max() > 0 for s in saved)
        resumed = refining_trainer(tmp_path, voxel_scene, "gs", max_steps=3, resume=True)
        resumed.restore(load_checkpoint(resumed.checkpoint_path()))
        assert all(torch.equal(a, b) for a, b in zip(saved, resumed.pipeline.poses.corrections, strict=True))
        loaded = load_trained_model(trainer.checkpoint_path(), scene=voxel_scene)
        assert all(torch.equal(a, b) for a, b in zip(saved, loaded.pipeline.poses.corrections, strict=True))

    def test_resume_with_refinement_turned_off_is_refused(self, tmp_path, voxel_scene):
        trainer = refining_trainer(tmp_path, voxel_scene, "gs")
        trainer.fit()
        trainer.save()
        config = quiet_config(BACKBONES["gs"](), tmp_path / "run", max_steps=2, resume=True)
        plain = Trainer(config, "gs", voxel_scene)
        with pytest.raises(ResumeMismatch, match="--camera-opt on"):
            plain.restore(load_checkpoint(plain.checkpoint_path()))


class TestRefinedPosesFile:
    def test_nothing_without_refinement(self, tmp_path, voxel_scene):
        config = quiet_config(BACKBONES["voxel-grid"](), tmp_path / "run", max_steps=2)
        trainer = Trainer(config, "voxel-grid", voxel_scene)
        assert write_refined_poses(trainer.pipeline, voxel_scene, tmp_path / "run", 2, quiet=True) is None
        assert not (tmp_path / "run" / "refined_poses.json").exists()

    def test_written_with_every_training_view(self, tmp_path, voxel_scene):
        trainer = refining_trainer(tmp_path, voxel_scene, "voxel-grid")
        trainer.train()  # the command's run: it writes OUT/refined_poses.json after the last checkpoint
        path = tmp_path / "run" / "refined_poses.json"
        report = json.loads(path.read_text())
        assert report["step"] == 2 and set(report["views"]) == {view.name for view in voxel_scene.train}
        index, name = next(
            (i, v.name)
            for i, v in enumerate(voxel_scene.train)
            if trainer.pipeline.poses.corrections[i].abs().max() > 0
        )
        entry = report["views"][name]
        expected = voxel_scene.train[index].camera.c2w @ trainer.pipeline.poses.correction(index).detach()
        torch.testing.assert_close(torch.tensor(entry["c2w_refined"]), expected)
        assert entry["rotation_degrees"] > 0
        assert not list(tmp_path.glob("run/*.tmp*"))  # written through a temporary file and renamed


class TestHeldOutPoseFit:
    """fit_held_out_pose (BARF's protocol): a held-out photo taken from a pose off the given one."""

    offset = torch.tensor([0.01, -0.01, 0.005, 0.006, -0.004, 0.005])  # scene radii, radians: 0.5 degrees

    def photo_off_the_given_pose(self, tmp_path, voxel_scene, backbone):
        trainer = refining_trainer(tmp_path, voxel_scene, backbone)
        view = voxel_scene.test[0]
        camera = view.camera.scaled(4)  # 64 px: enough texture to place a camera
        scale = voxel_scene.scene_info().extent
        truth = dataclasses.replace(
            camera, c2w=camera.c2w.float() @ pose_exp(torch.cat([self.offset[:3] * scale, self.offset[3:]]))
        )
        with trainer.pipeline.evaluating():
            photo = trainer.pipeline.render(truth, view.exposure).ldr
        return trainer.pipeline, camera, truth, photo, view.exposure

    @pytest.mark.parametrize("backbone, render_chunk", [("gs", None), ("voxel-grid", 512)])
    def test_finds_the_pose_the_photo_was_taken_from(self, tmp_path, voxel_scene, monkeypatch, backbone, render_chunk):
        """voxel-grid in pieces of 512 rays takes the path of backbones that render pixel batches (NeRF):
        a fixed subset of the left half's pixels."""
        pipeline, camera, truth, photo, exposure = self.photo_off_the_given_pose(tmp_path, voxel_scene, backbone)
        pipeline.backbone.render_chunk = render_chunk
        monkeypatch.setattr(appearance, "POSE_FIT_RAYS", 1024)
        pipeline.poses = None  # the given pose is the start
        response = camera_response(voxel_scene, None)
        with pipeline.evaluating():
            fitted, change = fit_held_out_pose(pipeline, voxel_scene, camera, photo, response, exposure)
            before = psnr(pipeline.render(camera, exposure).ldr, photo)
            after = psnr(pipeline.render(fitted, exposure).ldr, photo)
        error = torch.linalg.inv(truth.c2w.float()) @ fitted.c2w
        offset_degrees = math.degrees(float(self.offset[3:].norm()))
        assert after > before + 10
        assert rotation_angle_degrees(error[:3, :3]) < offset_degrees  # nearer the truth than the start
        assert change["appearance_fitted_pose_degrees"] > 0.5 * offset_degrees

    def test_starts_from_the_world_motion_of_the_nearest_training_view(self, tmp_path, voxel_scene, monkeypatch):
        pipeline, camera, _, photo, exposure = self.photo_off_the_given_pose(tmp_path, voxel_scene, "gs")
        monkeypatch.setattr(appearance, "POSE_FIT_STEPS", 0)
        with torch.no_grad():
            for index, correction in enumerate(pipeline.poses.corrections):
                correction.fill_(0.01 * (index + 1))
        centres = torch.stack([view.camera.c2w[:3, 3] for view in voxel_scene.train])
        nearest = int(torch.argmin((centres - camera.c2w[:3, 3]).norm(dim=-1)))
        given = voxel_scene.train[nearest].camera.c2w.float()
        scale = voxel_scene.scene_info().extent
        tangent = torch.full((6,), 0.01 * (nearest + 1))
        refined = given @ pose_exp(torch.cat([tangent[:3] * scale, tangent[3:]]))
        world_motion = refined @ torch.linalg.inv(given)  # what refinement did to the nearest view, in the world
        with pipeline.evaluating():
            fitted, _ = fit_held_out_pose(
                pipeline, voxel_scene, camera, photo, camera_response(voxel_scene, None), exposure
            )
        torch.testing.assert_close(fitted.c2w, world_motion @ camera.c2w.float(), atol=1e-5, rtol=0)

    def test_rules(self, tmp_path, voxel_scene):
        pipeline = refining_trainer(tmp_path, voxel_scene, "voxel-grid").pipeline
        assert pose_fit_runs(pipeline, "auto") and not pose_fit_runs(pipeline, "off")
        pipeline.poses = None
        assert not pose_fit_runs(pipeline, "auto") and pose_fit_runs(pipeline, "on")
        pipeline.backbone.differentiable_pose = False
        assert not pose_fit_runs(pipeline, "auto")
        with pytest.raises(FlagError, match="--eval-pose on"):
            pose_fit_runs(pipeline, "on")

    def test_a_refining_run_scores_held_out_views_with_their_poses_fitted(self, tmp_path, voxel_scene):
        metrics = refining_trainer(tmp_path, voxel_scene, "gs", max_eval_views=2).train()
        assert metrics["appearance_protocol"] == APPEARANCE_PROTOCOL + POSE_PROTOCOL
        assert all(row["appearance_fitted_pose_degrees"] >= 0 for row in metrics["views"])
        assert math.isfinite(metrics["ldr_psnr_appearance_fitted"])
        unfitted = refining_trainer(tmp_path / "off", voxel_scene, "gs", max_eval_views=2)
        unfitted.config.camera = dataclasses.replace(unfitted.config.camera, eval_pose="off")
        assert "appearance_fitted_pose_degrees" not in unfitted.train()["views"][0]
