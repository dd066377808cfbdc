"""Pose refinement through the 3DGS rasteriser: the C++ projection takes the pose as a constant, so a
refined pose moves the Gaussians instead (backbones.gs.rigid). Values, gradients and recovery."""

import dataclasses

import pytest
import torch
from gs_scenes import make_camera, random_gaussians

from backbones.gs import GaussianBackbone, GaussianConfig, reference
from backbones.gs.rasterizer import project_gaussians, rasterize, render_gaussians
from backbones.gs.reference import quaternion_to_rotation
from backbones.gs.rigid import camera_as_world_motion, move_gaussians, rotation_to_quaternion
from backbones.gs.sh import visible_colors
from mono_hdr_plugin.core.backbone import SceneInfo
from mono_hdr_plugin.core.camera_optimizer import PoseCorrections, pose_exp, rotation_angle_degrees, so3_exp

MOTION = pose_exp(torch.tensor([0.05, -0.03, 0.02, 0.02, 0.03, -0.04]), "SE3")


class TestRotationToQuaternion:
    @pytest.mark.parametrize(
        "axis_angle",
        [[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [3.1, 0.0, 0.0], [0.0, 3.14, 0.05], [0.02, 0.0, -3.13], [1.5, 1.5, 1.5]],
    )
    def test_is_the_rotation_the_rasteriser_reads(self, axis_angle):
        """Near 180 degrees too, where the trace-based formula divides by almost zero."""
        rotation = so3_exp(torch.tensor(axis_angle, dtype=torch.float64))
        quaternion = rotation_to_quaternion(rotation)
        torch.testing.assert_close(quaternion_to_rotation(quaternion[None])[0], rotation, atol=1e-12, rtol=0)


class TestMovingTheWorld:
    @pytest.mark.parametrize("backend", ["kernel", "torch"])
    def test_equals_rendering_with_the_moved_camera(self, backend):
        """Rendering through W with the Gaussians moved by D == rendering through W' = W D."""
        camera = make_camera()
        g = random_gaussians(300, seed=3)
        g["quats"][:3] = 0  # zero quaternions read as the identity, moved or not
        moved_camera = dataclasses.replace(camera, c2w=torch.linalg.inv(camera.w2c @ MOTION))
        direct, direct_alpha, _ = render_gaussians(
            g["means"], g["quats"], g["scales"], g["opacities"], g["values"], moved_camera, backend
        )
        means, quats = move_gaussians(g["means"], g["quats"], MOTION)
        moved, moved_alpha, _ = render_gaussians(
            means, quats, g["scales"], g["opacities"], g["values"], camera, backend
        )
        assert direct_alpha.max() > 0.5  # the Gaussians are in view
        torch.testing.assert_close(moved, direct, atol=2e-5, rtol=0)
        torch.testing.assert_close(moved_alpha, direct_alpha, atol=2e-5, rtol=0)


def sh_backbone(backend: str) -> GaussianBackbone:
    """Gaussians with view-dependent colour (SH degree 1 active), so the pose reaches the colours too."""
    torch.manual_seed(0)
    camera = make_camera()
    scene = SceneInfo(bounds_min=-torch.ones(3), bounds_max=torch.ones(3), train_cameras=[camera])
    backbone = GaussianBackbone(
        GaussianConfig(random_init_points=300, sh_degree=1, init_opacity=0.5, backend=backend), scene
    )
    g = random_gaussians(300, seed=5)
    with torch.no_grad():
        backbone.means.copy_(g["means"])
        backbone.quats.copy_(g["quats"])
        backbone.log_scales.copy_(torch.log(g["scales"] * 3))
        backbone.sh_rest.copy_(torch.randn_like(backbone.sh_rest) * 0.5)
    backbone.active_sh_degree = 1
    return backbone


def weighted_image(image: torch.Tensor) -> torch.Tensor:
    weights = torch.linspace(-1, 1, image.numel(), dtype=image.dtype).reshape(image.shape)
    return (image * weights).sum()


def pose_gradient(render) -> torch.Tensor:
    """d weighted_image(render(camera)) / d correction at the zero correction of one view."""
    poses = PoseCorrections(views=1, scene_scale=1.0, mode="SE3")
    weighted_image(render(poses.refine(make_camera(), 0))).backward()
    return poses.corrections[0].grad


def direct_render(backbone: GaussianBackbone, camera) -> torch.Tensor:
    """The torch twin with the pose differentiated where it enters (the view matrix, the SH view
    direction): the reference the world-moving path must match."""
    scales = torch.exp(backbone.log_scales)
    opacities = torch.sigmoid(backbone.opacity_logits)
    projected = project_gaussians(backbone.means, backbone.quats, scales, opacities, camera, backend="torch")
    colors = visible_colors(
        1, backbone.sh_dc, backbone.sh_rest, backbone.means, projected.index, camera.center, "torch"
    )
    return rasterize(projected, (colors + 0.5).clamp_min(0))[0]


def backbone_render(backbone: GaussianBackbone, camera) -> torch.Tensor:
    features = backbone.render_ldr_features(camera)
    return features.composite(features.colors)


class TestPoseGradient:
    @pytest.mark.parametrize("backend", ["kernel", "torch"])
    def test_moving_the_world_gives_the_gradient_of_moving_the_camera(self, backend):
        reference = pose_gradient(lambda camera: direct_render(sh_backbone("torch"), camera))
        moved = pose_gradient(lambda camera: backbone_render(sh_backbone(backend), camera))
        assert reference.abs().max() > 0
        torch.testing.assert_close(moved, reference, atol=2e-3 * reference.abs().max().item(), rtol=1e-3)

    def test_view_dependent_colour_adds_its_share(self):
        """Without the SH centre's gradient (the C++ SH kernel's backward) the rotation part would differ."""
        backbone = sh_backbone("kernel")
        with_sh = pose_gradient(lambda camera: backbone_render(backbone, camera))
        backbone.active_sh_degree = 0
        without = pose_gradient(lambda camera: backbone_render(backbone, camera))
        assert (with_sh - without).abs().max() > 1e-3 * with_sh.abs().max()

    def test_gradcheck_of_the_moved_world_in_double(self):
        """The torch twin in float64 (the kernel is float32): the pose's gradient through the motion of
        the world (rotation to quaternion, moved means and rotations) against finite differences."""
        camera = make_camera(width=20, height=16)
        g = random_gaussians(12, seed=11, dtype=torch.float64)
        scales = g["scales"] * 20  # a few pixels wide: no Gaussian crosses the culling edge within eps

        def image(tangent: torch.Tensor) -> torch.Tensor:
            refined = dataclasses.replace(camera, c2w=camera.c2w.double() @ pose_exp(tangent, "SE3"))
            fixed, motion = camera_as_world_motion(refined)
            means, quats = move_gaussians(g["means"], g["quats"], motion)
            intrinsics = (fixed.fx, fixed.fy, fixed.cx, fixed.cy, fixed.width, fixed.height, fixed.near)
            index, _, means2d, conics, depths, boxes = reference.project_gaussians_torch(
                means, quats, scales, g["opacities"], fixed.w2c, *intrinsics
            )
            offsets, ids = reference.bin_tiles_torch(boxes, depths.detach(), fixed.width, fixed.height)
            values = g["values"][index]
            args = (means2d, conics, g["opacities"][index], values, boxes, offsets, ids, fixed.width, fixed.height)
            return reference.rasterize_tiles_torch(*args)[0]

        tangent = torch.zeros(6, dtype=torch.float64, requires_grad=True)
        assert image(tangent).abs().max() > 0.1
        assert torch.autograd.gradcheck(image, (tangent,), eps=1e-6, atol=1e-6, rtol=1e-4)


class TestRecovery:
    def test_refinement_moves_a_perturbed_camera_toward_the_truth(self):
        """Fixed Gaussians, the photo taken from the true pose, the camera given 2 degrees and 0.05
        off: Adam on the correction alone must close most of the gap (a flipped sign would widen it)."""
        backbone = sh_backbone("kernel")
        backbone.active_sh_degree = 0
        for parameter in backbone.parameters():
            parameter.requires_grad_(False)
        truth = make_camera()
        with torch.no_grad():
            photo = backbone_render(backbone, truth)
        error = pose_exp(torch.tensor([0.04, -0.03, 0.02, 0.02, -0.025, 0.015]), "SO3xR3")
        given = dataclasses.replace(truth, c2w=truth.c2w @ error)
        poses = PoseCorrections(views=1, scene_scale=1.0)
        optimiser = torch.optim.Adam(poses.parameters(), lr=1e-2)

        def errors() -> tuple[float, float]:
            refined = poses.refine(given, 0).c2w.detach()
            relative = torch.linalg.inv(truth.c2w) @ refined
            return rotation_angle_degrees(relative[:3, :3]), float(relative[:3, 3].norm())

        rotation_before, translation_before = errors()
        for _ in range(100):
            optimiser.zero_grad()
            (backbone_render(backbone, poses.refine(given, 0)) - photo).square().mean().backward()
            optimiser.step()
        rotation_after, translation_after = errors()
        assert rotation_after < 0.3 * rotation_before
        assert translation_after < 0.3 * translation_before
