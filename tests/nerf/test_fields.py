import math

import torch

from backbones.nerf import GridFieldConfig, MlpFieldConfig
from backbones.nerf.fields import (DensityGrid, GridRadianceField, MlpRadianceField, activate_density,
                                   encoded_size, grid_resolutions, positional_encoding, sample_grid)


class TestPositionalEncoding:
    def test_shape(self):
        assert positional_encoding(torch.rand(7, 5, 3), 10).shape == (7, 5, 63)
        assert encoded_size(4) == 27

    def test_known_values(self):
        encoded = positional_encoding(torch.tensor([[math.pi / 2]]), 2)
        # [x, sin(x), cos(x), sin(2x), cos(2x)]
        torch.testing.assert_close(encoded, torch.tensor([[math.pi / 2, 1.0, 0.0, 0.0, -1.0]]), atol=1e-6, rtol=0)

    def test_zero_frequencies_is_identity(self):
        x = torch.rand(4, 3)
        torch.testing.assert_close(positional_encoding(x, 0), x)


class TestActivateDensity:
    def test_non_negative_and_finite(self):
        raw = torch.tensor([-1e4, -1.0, 0.0, 1.0, 1e4])
        for activation in ("relu", "softplus"):
            density = activate_density(raw, activation)
            assert (density >= 0).all() and torch.isfinite(density).all()


class TestMlpRadianceField:
    def test_official_architecture(self):
        field = MlpRadianceField(MlpFieldConfig())
        assert len(field.position_layers) == 8
        assert field.position_layers[0].in_features == 63
        assert field.position_layers[5].in_features == 256 + 63
        assert field.view_layer.in_features == 256 + 27 and field.view_layer.out_features == 128

    def test_shapes_and_non_negative_density(self):
        field = MlpRadianceField(MlpFieldConfig(width=32))
        directions = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
        density, raw_color = field(torch.rand(50, 3) * 2 - 1, directions)
        assert density.shape == (50,) and raw_color.shape == (50, 3)
        assert (density >= 0).all()

    def test_colour_depends_on_direction(self):
        field = MlpRadianceField(MlpFieldConfig(width=32))
        positions = torch.zeros(2, 3)
        density, raw_color = field(positions, torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
        assert density[0] == density[1]
        assert not torch.allclose(raw_color[0], raw_color[1])


class TestGridRadianceField:
    def test_resolutions_are_geometric(self):
        assert grid_resolutions(GridFieldConfig(levels=4, min_resolution=16, max_resolution=128)) == [16, 32, 64, 128]
        assert grid_resolutions(GridFieldConfig(levels=1, max_resolution=32)) == [32]

    def test_sample_grid_is_trilinear(self):
        grid = torch.arange(8, dtype=torch.float32).reshape(1, 1, 2, 2, 2)
        # Corners: value = 4 z + 2 y + x with (x, y, z) in {0, 1}; the centre averages them.
        values = sample_grid(grid, torch.tensor([[0.0, 0.0, 0.0], [1.0, -1.0, -1.0], [-1.0, -1.0, 1.0]]))
        torch.testing.assert_close(values[:, 0], torch.tensor([3.5, 1.0, 4.0]))

    def test_shapes_and_gradients_reach_grids(self):
        field = GridRadianceField(GridFieldConfig(levels=2, min_resolution=4, max_resolution=8, hidden_width=16))
        directions = torch.nn.functional.normalize(torch.randn(40, 3), dim=-1)
        density, raw_color = field(torch.rand(40, 3) * 2 - 1, directions)
        assert density.shape == (40,) and raw_color.shape == (40, 3)
        (density.sum() + raw_color.sum()).backward()
        assert all(grid.grad is not None and grid.grad.abs().sum() > 0 for grid in field.grids)
        assert field.density(torch.zeros(3, 3)).shape == (3,)


class TestDensityGrid:
    def test_starts_empty_and_unfilled(self):
        grid = DensityGrid(8)
        assert not grid.filled
        assert torch.equal(grid.lookup(torch.rand(5, 3)), torch.zeros(5))

    def test_update_caches_density(self):
        grid = DensityGrid(16)
        grid.update(lambda p: 10.0 * (p.norm(dim=-1) < 0.5).float(), decay=0.9)
        assert grid.filled
        assert grid.lookup(torch.zeros(1, 3)).item() > 5.0
        assert grid.lookup(torch.tensor([[0.95, 0.95, 0.95]])).item() == 0.0

    def test_decay_forgets_slowly(self):
        grid = DensityGrid(4)
        grid.update(lambda p: torch.full(p.shape[:1], 2.0), decay=0.5)
        grid.update(lambda p: torch.zeros(p.shape[0]), decay=0.5)
        torch.testing.assert_close(grid.densities, torch.full_like(grid.densities, 1.0))
