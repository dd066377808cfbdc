import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from backbones.nerf.sampling import intersect_box, ray_segments, resample_occupied, sample_pdf, sample_stratified

BOX = (-torch.ones(3), torch.ones(3))


class TestIntersectBox:
    def test_known_values(self):
        t_enter, t_exit = intersect_box(torch.tensor([[-3.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]]), *BOX)
        torch.testing.assert_close(t_enter, torch.tensor([2.0]))
        torch.testing.assert_close(t_exit, torch.tensor([4.0]))

    def test_diagonal_ray(self):
        direction = torch.ones(1, 3) / math.sqrt(3.0)
        t_enter, t_exit = intersect_box(-2.0 * torch.ones(1, 3), direction, *BOX)
        torch.testing.assert_close(t_enter, torch.tensor([math.sqrt(3.0)]))
        torch.testing.assert_close(t_exit, torch.tensor([3.0 * math.sqrt(3.0)]))

    def test_parallel_ray_inside_slab_hits_finitely(self):
        # Parallel to the y and z faces, origin between them (and exactly on a face plane).
        origins = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 1.0, -1.0]])
        directions = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
        t_enter, t_exit = intersect_box(origins, directions, *BOX)
        assert torch.isfinite(t_enter).all() and torch.isfinite(t_exit).all()
        torch.testing.assert_close(t_enter, torch.tensor([2.0, 2.0]))
        torch.testing.assert_close(t_exit, torch.tensor([4.0, 4.0]))

    def test_parallel_ray_outside_slab_misses(self):
        t_enter, t_exit = intersect_box(torch.tensor([[-3.0, 2.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]]), *BOX)
        assert torch.isfinite(t_enter).all() and torch.isfinite(t_exit).all()
        assert (t_exit < t_enter).all()

    def test_origin_inside(self):
        t_enter, t_exit = intersect_box(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, -1.0]]), *BOX)
        assert t_enter.item() < 0 < t_exit.item()
        torch.testing.assert_close(t_exit, torch.tensor([1.0]))


class TestRaySegments:
    def test_without_box_is_near_far(self):
        t_near, t_far = ray_segments(torch.zeros(2, 3), torch.tensor([[1.0, 0, 0], [0, 1.0, 0]]), 0.5, 6.0, None)
        torch.testing.assert_close(t_near, torch.full((2,), 0.5))
        torch.testing.assert_close(t_far, torch.full((2,), 6.0))

    def test_clipped_to_box(self):
        t_near, t_far = ray_segments(torch.tensor([[-3.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]]), 0.5, 3.0, BOX)
        torch.testing.assert_close(t_near, torch.tensor([2.0]))
        torch.testing.assert_close(t_far, torch.tensor([3.0]))

    def test_origin_inside_box_starts_at_near(self):
        t_near, t_far = ray_segments(torch.zeros(1, 3), torch.tensor([[1.0, 0.0, 0.0]]), 0.1, 6.0, BOX)
        torch.testing.assert_close(t_near, torch.tensor([0.1]))
        torch.testing.assert_close(t_far, torch.tensor([1.0]))

    def test_miss_and_far_equal_near_give_zero_length(self):
        origins = torch.tensor([[-3.0, 5.0, 0.0], [-3.0, 0.0, 0.0]])
        directions = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
        t_near, t_far = ray_segments(origins, directions, 2.5, 2.5, BOX)
        assert torch.isfinite(t_near).all()
        torch.testing.assert_close(t_far, t_near)


class TestSampleStratified:
    def test_deterministic_is_evenly_spaced_from_near_to_far(self):
        t = sample_stratified(torch.tensor([1.0]), torch.tensor([3.0]), 5, perturb=False)
        torch.testing.assert_close(t, torch.tensor([[1.0, 1.5, 2.0, 2.5, 3.0]]))

    def test_perturbed_sorted_and_within_bounds(self):
        t_near, t_far = torch.rand(100), 1.0 + torch.rand(100)
        t = sample_stratified(t_near, t_far, 16, perturb=True)
        assert t.shape == (100, 16)
        assert (t[:, 1:] >= t[:, :-1]).all()
        assert (t >= t_near[:, None]).all() and (t <= t_far[:, None]).all()
        assert not torch.equal(t, sample_stratified(t_near, t_far, 16, perturb=False))

    def test_zero_length(self):
        t = sample_stratified(torch.full((3,), 2.0), torch.full((3,), 2.0), 4, perturb=True)
        torch.testing.assert_close(t, torch.full((3, 4), 2.0))


class TestSamplePdf:
    def test_concentrates_where_weights_are(self):
        edges = torch.linspace(0.0, 1.0, 11).expand(50, 11).contiguous()
        weights = torch.zeros(50, 10)
        weights[:, 6] = 1.0
        samples = sample_pdf(edges, weights, 64, deterministic=False)
        inside = ((samples >= 0.6) & (samples <= 0.7)).float().mean()
        assert inside > 0.99

    def test_follows_relative_weights(self):
        edges = torch.tensor([[0.0, 1.0, 2.0]]).expand(200, 3).contiguous()
        weights = torch.tensor([[1.0, 3.0]]).expand(200, 2)
        samples = sample_pdf(edges, weights, 100, deterministic=False)
        assert abs((samples > 1.0).float().mean().item() - 0.75) < 0.02

    def test_zero_weights_give_uniform_samples(self):
        edges = torch.linspace(2.0, 4.0, 9)[None]
        samples = sample_pdf(edges, torch.zeros(1, 8), 5, deterministic=True)
        torch.testing.assert_close(samples, torch.linspace(2.0, 4.0, 5)[None])

    def test_zero_width_bins_stay_finite(self):
        samples = sample_pdf(torch.full((2, 5), 3.0), torch.rand(2, 4), 8, deterministic=False)
        torch.testing.assert_close(samples, torch.full((2, 8), 3.0))

    @settings(max_examples=30, deadline=None)
    @given(st.integers(1, 12), st.integers(1, 20), st.booleans(), st.integers(0, 2**31 - 1))
    def test_sorted_within_bins(self, num_bins, num_samples, deterministic, seed):
        generator = torch.Generator().manual_seed(seed)
        edges = torch.rand(4, num_bins + 1, generator=generator).cumsum(-1)
        weights = torch.rand(4, num_bins, generator=generator) * (torch.rand(4, num_bins, generator=generator) > 0.5)
        samples = sample_pdf(edges, weights, num_samples, deterministic)
        assert samples.shape == (4, num_samples)
        assert torch.isfinite(samples).all()
        assert (samples[:, 1:] >= samples[:, :-1]).all()
        assert (samples >= edges[:, :1] - 1e-6).all() and (samples <= edges[:, -1:] + 1e-6).all()


class TestResampleOccupied:
    def test_samples_follow_the_weight_into_its_bin(self):
        # Four marched bins of length 0.5 at t = 1.25, 1.75, 3.25, 3.75 (a gap between the pairs);
        # all weight in the third bin [3.0, 3.5].
        t = torch.tensor([[1.25, 1.75, 3.25, 3.75]])
        delta = torch.full((1, 4), 0.5)
        weights = torch.tensor([[0.0, 0.0, 0.9, 0.0]])
        new_t, new_delta = resample_occupied(t, delta, torch.full((1, 4), 0.5), weights, 100, deterministic=True)
        inside = ((new_t >= 3.0) & (new_t <= 3.5)).float().mean()
        assert inside > 0.97  # 99 % of the pdf, up to the evenly spread 1 %
        assert (new_t[:, 1:] >= new_t[:, :-1]).all()

    def test_deltas_add_up_to_the_occupied_length_after_the_first_sample(self):
        t = torch.tensor([[1.25, 1.75, 3.25, 3.75]])
        delta = torch.full((1, 4), 0.5)
        new_t, new_delta = resample_occupied(
            t, delta, torch.full((1, 4), 0.5), torch.zeros(1, 4), 8, deterministic=True
        )
        # Zero weights: evenly spread over the occupied length 2 from its start, 0.25 each.
        torch.testing.assert_close(new_delta, torch.full((1, 8), 0.25))
        # Occupied length 2 in two pieces: evenly spaced quantiles map across the gap [2, 3].
        expected_s = torch.arange(8) * 0.25
        expected_t = torch.where(expected_s < 1.0, 1.0 + expected_s, 2.0 + expected_s)
        torch.testing.assert_close(new_t[0], expected_t)

    def test_jittered_marching_positions_are_respected(self):
        # A sample jittered to 10 % of its bin: the bin still starts at t - 0.1 * delta.
        t = torch.tensor([[2.05]])
        new_t, _ = resample_occupied(
            t, torch.tensor([[0.5]]), torch.tensor([[0.1]]), torch.ones(1, 1), 3, deterministic=True
        )
        torch.testing.assert_close(new_t[0], torch.tensor([2.0, 2.0 + 1 / 6, 2.0 + 2 / 6]))

    def test_rays_without_occupied_length_get_zero_deltas(self):
        new_t, new_delta = resample_occupied(
            torch.full((2, 3), 5.0),
            torch.zeros(2, 3),
            torch.full((2, 3), 0.5),
            torch.zeros(2, 3),
            4,
            deterministic=False,
        )
        assert torch.isfinite(new_t).all() and torch.equal(new_delta, torch.zeros(2, 4))
