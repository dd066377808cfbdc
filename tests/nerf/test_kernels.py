"""The grid-field C++ kernels against their plain-torch twins: values, gradients, gradcheck."""

import math

import pytest
import torch

from backbones.nerf.kernels import grid_encode, march_rays
from backbones.nerf.reference import grid_encode_reference, march_rays_reference
from backbones.nerf.sampling import ray_segments


def levels(resolutions: list[int]) -> tuple[torch.Tensor, torch.Tensor, int]:
    sizes = torch.tensor([r**3 for r in resolutions])
    return torch.tensor(resolutions), torch.cumsum(sizes, 0) - sizes, int(sizes.sum())


class TestGridEncode:
    @pytest.mark.parametrize("features", [1, 2, 4])
    @pytest.mark.parametrize("resolutions", [[2], [3, 5], [4, 7, 16]])
    def test_values_and_gradients_match_grid_sample(self, features, resolutions):
        res, offsets, rows = levels(resolutions)
        table = torch.randn(rows, features, requires_grad=True)
        # Some positions outside the cube: both clamp to the border.
        positions = torch.rand(300, 3) * 2.4 - 1.2
        fast = grid_encode(positions, table, res, offsets)
        slow = grid_encode_reference(positions, table, res, offsets)
        assert fast.shape == (300, len(resolutions) * features)
        torch.testing.assert_close(fast, slow, atol=1e-5, rtol=1e-5)
        upstream = torch.randn_like(fast)
        (grad_fast,) = torch.autograd.grad(fast, table, upstream)
        (grad_slow,) = torch.autograd.grad(slow, table, upstream)
        torch.testing.assert_close(grad_fast, grad_slow, atol=1e-4, rtol=1e-4)

    def test_known_values_at_vertices_and_centre(self):
        res, offsets, rows = levels([2])
        table = torch.arange(8, dtype=torch.float32)[:, None]  # vertex (x, y, z) holds x + 2 y + 4 z
        positions = torch.tensor([[-1.0, -1.0, -1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
        torch.testing.assert_close(
            grid_encode(positions, table, res, offsets)[:, 0], torch.tensor([0.0, 1.0, 6.0, 3.5])
        )

    def test_gradcheck_float64(self):
        res, offsets, rows = levels([2, 3])
        table = torch.randn(rows, 2, dtype=torch.float64, requires_grad=True)
        positions = torch.rand(6, 3, dtype=torch.float64) * 2 - 1
        assert torch.autograd.gradcheck(lambda t: grid_encode(positions, t, res, offsets), (table,))

    def test_table_gradient_sums_to_upstream(self):
        # Trilinear weights sum to 1 at every position: the table gradient's total is the upstream total.
        res, offsets, rows = levels([5])
        table = torch.zeros(rows, 1, requires_grad=True)
        out = grid_encode(torch.rand(50, 3) * 2 - 1, table, res, offsets)
        out.sum().backward()
        torch.testing.assert_close(table.grad.sum(), torch.tensor(50.0))

    def test_bad_table_raises(self):
        res, offsets, rows = levels([4])
        with pytest.raises(RuntimeError, match="does not fit"):
            grid_encode(torch.zeros(1, 3), torch.zeros(rows - 1, 2), res, offsets)


def random_rays(count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    origins = torch.randn(count, 3, generator=generator) * 3
    directions = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator) - 0.3 * origins, dim=-1)
    return origins, directions


class TestMarchRays:
    @pytest.mark.parametrize("stratified", [False, True])
    @pytest.mark.parametrize("size,fill", [(1, 1.0), (8, 0.4), (16, 0.1)])
    def test_matches_twin(self, stratified, size, fill):
        origins, directions = random_rays(2000, seed=size)
        occupancy = torch.rand(size, size, size, generator=torch.Generator().manual_seed(1)) < fill
        box = (-1.4 * torch.ones(3), 1.4 * torch.ones(3))
        t_near, t_far = ray_segments(origins, directions, 0.1, 9.0, box)
        center = torch.tensor([0.1, 0.2, -0.1])
        jitter = torch.rand(2000, 24) if stratified else None
        args = (origins, directions, t_near, t_far, occupancy, center, 1.5, 0.04, 24, jitter)
        t, delta, counts = march_rays(*args)
        t_ref, delta_ref, counts_ref = march_rays_reference(*args)
        assert counts.gt(0).sum() > 100
        assert torch.equal(counts, counts_ref)
        torch.testing.assert_close(t, t_ref, atol=2e-5, rtol=0)
        torch.testing.assert_close(delta, delta_ref, atol=2e-5, rtol=0)

    def test_samples_lie_in_occupied_cells_and_cover_them(self):
        origins = torch.nn.functional.normalize(torch.randn(500, 3), dim=-1) * 3
        directions = torch.nn.functional.normalize(torch.rand(500, 3) - 0.5 - origins, dim=-1)  # at the centre
        occupancy = torch.zeros(8, 8, 8, dtype=torch.bool)
        occupancy[2:5, 3:6, 1:4] = True
        t_near, t_far = ray_segments(origins, directions, 0.0, 20.0, (-torch.ones(3), torch.ones(3)))
        t, delta, counts = march_rays(
            origins, directions, t_near, t_far, occupancy, torch.zeros(3), 1.0, 0.01, 64, torch.rand(500, 64)
        )
        real = torch.arange(64) < counts[:, None]
        points = origins[:, None] + t[..., None] * directions[:, None]
        cells = ((points[real] + 1) * 4).floor().long().clamp(0, 7)
        assert counts.gt(0).sum() > 100
        assert occupancy[cells[:, 2], cells[:, 1], cells[:, 0]].float().mean() > 0.999
        # The deltas of a ray add up to its occupied length, which is at most its box segment.
        assert (delta.sum(-1) <= (t_far - t_near) + 1e-4).all()

    def test_sample_count_follows_occupied_length(self):
        # One ray along x through the cube centre: occupied length 2, min_step 0.1 -> 20 samples,
        # or the cap when it is lower; bins of equal length 2 / n.
        origins, directions = torch.tensor([[-3.0, 0.01, 0.01]]), torch.tensor([[1.0, 0.0, 0.0]])
        occupancy = torch.ones(4, 4, 4, dtype=torch.bool)
        for cap, expected in ((64, 20), (8, 8)):
            t, delta, counts = march_rays(
                origins,
                directions,
                torch.tensor([2.0]),
                torch.tensor([4.0]),
                occupancy,
                torch.zeros(3),
                1.0,
                0.1,
                cap,
                None,
            )
            assert counts.item() == expected
            torch.testing.assert_close(delta[0, :expected], torch.full((expected,), 2.0 / expected))
            torch.testing.assert_close(t[0, :expected], 2.0 + (torch.arange(expected) + 0.5) * 2.0 / expected)

    def test_empty_grid_and_missing_rays_give_no_samples(self):
        origins, directions = random_rays(100, seed=4)
        t_near, t_far = ray_segments(origins, directions, 0.0, 20.0, (-torch.ones(3), torch.ones(3)))
        _, _, counts = march_rays(
            origins,
            directions,
            t_near,
            t_far,
            torch.zeros(4, 4, 4, dtype=torch.bool),
            torch.zeros(3),
            1.0,
            0.01,
            16,
            None,
        )
        assert counts.sum() == 0
        _, _, counts = march_rays(
            origins,
            directions,
            t_near,
            t_near,
            torch.ones(4, 4, 4, dtype=torch.bool),
            torch.zeros(3),
            1.0,
            0.01,
            16,
            None,
        )
        assert counts.sum() == 0

    def test_ray_along_a_cell_plane_is_finite(self):
        # Runs exactly on the plane y = 0 between two cell layers, parallel to two axes.
        origins, directions = torch.tensor([[-3.0, 0.0, 0.5]]), torch.tensor([[1.0, 0.0, 0.0]])
        t, delta, counts = march_rays(
            origins,
            directions,
            torch.tensor([2.0]),
            torch.tensor([4.0]),
            torch.ones(4, 4, 4, dtype=torch.bool),
            torch.zeros(3),
            1.0,
            0.25,
            16,
            None,
        )
        assert counts.item() == 8 and torch.isfinite(t).all() and torch.isfinite(delta).all()
        assert math.isclose(delta.sum().item(), 2.0, rel_tol=1e-5)
