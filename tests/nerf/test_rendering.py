import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from backbones.nerf.rendering import compositing_weights, make_composite, make_packed_composite, sample_deltas
from backbones.nerf.sampling import sample_stratified


class TestSampleDeltas:
    def test_distance_to_next_and_last_to_far(self):
        deltas = sample_deltas(torch.tensor([[1.0, 1.5, 3.0]]), torch.tensor([4.0]))
        torch.testing.assert_close(deltas, torch.tensor([[0.5, 1.5, 1.0]]))

    def test_never_negative(self):
        deltas = sample_deltas(torch.tensor([[2.0, 2.0]]), torch.tensor([1.0]))
        assert (deltas >= 0).all()


class TestCompositingWeights:
    def test_constant_density_slab(self):
        # Constant sigma on [near, far]: transmittance exp(-sigma d), accumulation 1 - exp(-sigma L).
        sigma, near, far = 0.7, 2.0, 5.0
        t = sample_stratified(torch.tensor([near]), torch.tensor([far]), 64, perturb=True)
        weights = compositing_weights(torch.full_like(t, sigma), sample_deltas(t, torch.tensor([far])))
        expected_total = 1.0 - math.exp(-sigma * (far - t[0, 0].item()))
        torch.testing.assert_close(weights.sum(), torch.tensor(expected_total))
        transmittance = 1.0 - torch.cumsum(weights, -1) + weights
        torch.testing.assert_close(transmittance, torch.exp(-sigma * (t - t[:, :1])))

    def test_empty_ray(self):
        densities = torch.zeros(2, 16, requires_grad=True)
        weights = compositing_weights(densities, torch.full((2, 16), 0.1))
        weights.sum().backward()
        assert torch.equal(weights, torch.zeros(2, 16))
        assert torch.isfinite(densities.grad).all()

    def test_fully_opaque_first_sample(self):
        densities = torch.tensor([[1e8, 3.0, 5.0, 0.0]])
        weights = compositing_weights(densities, torch.full((1, 4), 0.5))
        torch.testing.assert_close(weights, torch.tensor([[1.0, 0.0, 0.0, 0.0]]))

    def test_zero_length_ray(self):
        densities = torch.rand(3, 8, requires_grad=True)
        weights = compositing_weights(densities, torch.zeros(3, 8))
        weights.sum().backward()
        assert torch.equal(weights, torch.zeros(3, 8))
        assert torch.isfinite(densities.grad).all()

    def test_late_opaque_sample_keeps_earlier_absorption(self):
        weights = compositing_weights(torch.tensor([[1.0, 1e30]]), torch.tensor([[0.5, 1.0]]))
        torch.testing.assert_close(weights[0, 1], torch.tensor(math.exp(-0.5)))

    @settings(max_examples=40, deadline=None)
    @given(st.integers(1, 32), st.floats(0.0, 1e4), st.integers(0, 2**31 - 1))
    def test_weights_sum_at_most_one(self, num_samples, scale, seed):
        generator = torch.Generator().manual_seed(seed)
        densities = scale * torch.rand(5, num_samples, generator=generator)
        weights = compositing_weights(densities, torch.rand(5, num_samples, generator=generator))
        assert torch.isfinite(weights).all() and (weights >= 0).all()
        assert (weights.sum(-1) <= 1.0 + 1e-6).all()

    def test_gradcheck(self):
        densities = torch.rand(2, 5, dtype=torch.float64, requires_grad=True)
        deltas = torch.rand(2, 5, dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda d: compositing_weights(d, deltas), (densities,))


class TestMakeComposite:
    def test_shape_and_values(self):
        weights = torch.rand(6, 4) / 4
        values = torch.rand(6, 4, 5)
        image = make_composite(weights, (2, 3), torch.zeros(3))(values)
        assert image.shape == (2, 3, 5)
        torch.testing.assert_close(image.reshape(6, 5), (weights[..., None] * values).sum(1))

    def test_background_fills_empty_rays_in_each_group_of_three(self):
        background = torch.tensor([0.2, 0.4, 0.6])
        composite = make_composite(torch.zeros(2, 3), (2,), background)
        torch.testing.assert_close(composite(torch.rand(2, 3, 6)), background.repeat(2).expand(2, 6))

    def test_background_behind_partial_accumulation(self):
        weights = torch.tensor([[0.25, 0.25]])
        image = make_composite(weights, (1,), torch.ones(3))(torch.zeros(1, 2, 3))
        torch.testing.assert_close(image, torch.full((1, 3), 0.5))

    def test_wrong_value_shape_raises(self):
        composite = make_composite(torch.rand(4, 3), (4,), torch.zeros(3))
        with pytest.raises(ValueError, match="rays, samples, channels"):
            composite(torch.rand(4, 5, 3))

    def test_background_needs_groups_of_three(self):
        composite = make_composite(torch.rand(4, 3), (4,), torch.ones(3))
        with pytest.raises(ValueError, match="groups of 3"):
            composite(torch.rand(4, 3, 2))

    def test_gradients_reach_values_and_weights(self):
        weights = torch.rand(3, 4, requires_grad=True)
        values = torch.rand(3, 4, 6, requires_grad=True)
        make_composite(weights, (3,), torch.ones(3))(values).sum().backward()
        assert weights.grad.abs().sum() > 0 and values.grad.abs().sum() > 0


class TestMakePackedComposite:
    def test_sums_samples_per_ray(self):
        weights = torch.tensor([0.5, 0.25, 1.0])
        composite = make_packed_composite(
            weights, torch.tensor([0, 0, 2]), torch.tensor([0.75, 0.0, 1.0]), (3,), torch.zeros(3)
        )
        values = torch.tensor([[1.0], [2.0], [3.0]])
        torch.testing.assert_close(composite(values), torch.tensor([[1.0], [0.0], [3.0]]))

    def test_background_behind_accumulation(self):
        composite = make_packed_composite(
            torch.tensor([0.5]), torch.tensor([1]), torch.tensor([0.0, 0.5]), (1, 2), torch.ones(3)
        )
        image = composite(torch.zeros(1, 6))
        torch.testing.assert_close(image, torch.tensor([[[1.0] * 6, [0.5] * 6]]))

    def test_no_samples(self):
        composite = make_packed_composite(
            torch.zeros(0), torch.zeros(0, dtype=torch.long), torch.zeros(4), (2, 2), torch.zeros(3)
        )
        torch.testing.assert_close(composite(torch.zeros(0, 6)), torch.zeros(2, 2, 6))

    def test_wrong_value_shape_raises(self):
        composite = make_packed_composite(
            torch.rand(5), torch.zeros(5, dtype=torch.long), torch.ones(1), (1,), torch.zeros(3)
        )
        with pytest.raises(ValueError, match="packed samples"):
            composite(torch.rand(4, 3))
