"""The environment map: directions to texels worked by hand, the seam, the pole frame, gradients."""

import math

import pytest
import torch

from mono_hdr_plugin.core.environment import EnvironmentMap, direction_to_uv, sky_frame, up_from_cameras


def texel_direction(row: int, column: int, width: int) -> torch.Tensor:
    """World direction (z up, azimuth from +x towards +y) of a texel centre of a width x width/2 map."""
    azimuth = -math.pi + (column + 0.5) * 2 * math.pi / width
    elevation = math.pi / 2 - (row + 0.5) * math.pi / (width // 2)
    return torch.tensor(
        [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
    )


class TestSkyFrame:
    @pytest.mark.parametrize("up", [(0.0, 0.0, 1.0), (0.0, -1.0, 0.0), (0.3, 0.4, -0.2), (1.0, 0.0, 0.0)])
    def test_is_a_rotation_whose_z_is_up(self, up):
        frame = sky_frame(torch.tensor(up))
        torch.testing.assert_close(frame @ frame.T, torch.eye(3), atol=1e-6, rtol=0)
        torch.testing.assert_close(float(torch.det(frame)), 1.0, atol=1e-6, rtol=0)
        torch.testing.assert_close(frame[2], torch.tensor(up) / torch.tensor(up).norm(), atol=1e-6, rtol=0)

    def test_cameras_held_upright_give_world_up(self):
        # OpenCV cameras looking along +x, +y and -x with world z up: their y axis is -z.
        c2ws = torch.eye(4).repeat(3, 1, 1)
        for c2w, forward in zip(c2ws, ([1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0])):
            forward = torch.tensor(forward)
            down = torch.tensor([0.0, 0.0, -1.0])
            c2w[:3, 0], c2w[:3, 1], c2w[:3, 2] = torch.linalg.cross(down, forward), down, forward
        torch.testing.assert_close(up_from_cameras(c2ws), torch.tensor([0.0, 0.0, 1.0]))


class TestDirectionToUv:
    def test_straight_up_down_and_the_axes(self):
        frame = torch.eye(3)
        directions = torch.tensor([[0, 0, 1.0], [0, 0, -2.0], [1.0, 0, 0], [0, 1.0, 0], [-1.0, 1e-9, 0]])
        expected = torch.tensor([[0.0, -1], [0, 1], [0, 0], [0.5, 0], [1, 0]])
        torch.testing.assert_close(direction_to_uv(directions, frame), expected, atol=1e-6, rtol=0)


class TestEnvironmentMap:
    def test_a_texel_is_seen_in_its_direction_and_nowhere_far_from_it(self):
        env = EnvironmentMap(torch.tensor([0.0, 0, 1]), width=32, levels=1)
        with torch.no_grad():
            env.textures[0].zero_()
            env.textures[0][:, 5, 11] = torch.tensor([7.0, 8.0, 9.0])
        torch.testing.assert_close(env(texel_direction(5, 11, 32)), torch.tensor([7.0, 8.0, 9.0]))
        assert float(env(texel_direction(5, 13, 32)).detach().abs().max()) == 0.0
        assert float(env(texel_direction(7, 11, 32)).detach().abs().max()) == 0.0

    def test_is_continuous_across_the_seam(self):
        env = EnvironmentMap(torch.tensor([0.0, 0, 1]), width=16, levels=1)
        with torch.no_grad():
            env.textures[0].normal_()
        either_side = env(torch.tensor([[-1.0, -1e-5, 0.2], [-1.0, 1e-5, 0.2]])).detach()
        torch.testing.assert_close(either_side[0], either_side[1], atol=1e-3, rtol=0)
        # exactly at the seam (azimuth pi), on a row's centre: the mean of the last and the first column
        row = 3
        elevation = math.pi / 2 - (row + 0.5) * math.pi / 8
        seam = env(torch.tensor([-math.cos(elevation), 0.0, math.sin(elevation)])).detach()
        texture = env.textures[0].detach()
        torch.testing.assert_close(seam, 0.5 * (texture[:, row, 0] + texture[:, row, -1]), atol=1e-5, rtol=0)

    def test_starts_at_its_initial_value_everywhere(self):
        env = EnvironmentMap(torch.tensor([0.0, 1.0, 0.0]), width=64, levels=3, initial=-0.25)
        values = env(torch.randn(100, 3))
        torch.testing.assert_close(values, torch.full((100, 3), -0.25))

    def test_gradcheck(self):
        env = EnvironmentMap(torch.tensor([0.0, 0, 1]), width=16, levels=2).double()
        directions = torch.randn(5, 3, dtype=torch.float64)
        textures = [torch.randn_like(t, requires_grad=True) for t in env.textures]

        def lookup(*values):
            return torch.func.functional_call(env, {f"textures.{i}": v for i, v in enumerate(values)}, (directions,))

        assert torch.autograd.gradcheck(lookup, tuple(textures))

    @pytest.mark.parametrize("width, levels", [(2, 1), (16, 3), (15, 1)])
    def test_refuses_a_pyramid_too_small(self, width, levels):
        with pytest.raises(ValueError, match="environment map"):
            EnvironmentMap(torch.tensor([0.0, 0, 1]), width=width, levels=levels)
