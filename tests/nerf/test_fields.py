import math

import torch

from backbones.nerf import GridFieldConfig, MlpFieldConfig
from backbones.nerf.fields import (
    GridRadianceField,
    MlpRadianceField,
    OccupancyGrid,
    activate_density,
    bounded_logit,
    encoded_size,
    grid_resolutions,
    positional_encoding,
)
from backbones.nerf.reference import grid_encode_reference


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


class TestBoundedLogit:
    def test_small_logits_pass_and_large_ones_stop_at_the_bound(self):
        logits = torch.tensor([-1e4, -200.0, -0.5, 0.0, 0.5, 3.0, 200.0, 1e4])
        bounded = bounded_logit(logits, 8.0)
        torch.testing.assert_close(bounded[2:5], logits[2:5], atol=2e-3, rtol=0)  # x - x^3 / (3 b^2)
        assert abs(float(bounded[5]) - 8.0 * math.tanh(3.0 / 8.0)) < 1e-5 and float(bounded[5]) > 2.8
        torch.testing.assert_close(bounded[[0, 1, 6, 7]], torch.tensor([-8.0, -8.0, 8.0, 8.0]))
        assert (torch.diff(bounded) >= 0).all()  # order kept: a brighter logit never lifts to less

    def test_bound_zero_is_the_logit(self):
        logits = torch.tensor([-300.0, 0.1, 250.0])
        assert bounded_logit(logits, 0.0) is logits

    def test_gradcheck(self):
        logits = torch.tensor([-20.0, -1.0, 0.3, 7.0, 30.0], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda x: bounded_logit(x, 8.0), (logits,))


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

    def test_table_holds_every_level_one_after_another(self):
        field = GridRadianceField(GridFieldConfig(levels=3, min_resolution=4, max_resolution=16, features_per_level=2))
        assert field.resolutions.tolist() == [4, 8, 16]
        assert field.offsets.tolist() == [0, 64, 64 + 512]
        assert field.table.shape == (64 + 512 + 4096, 2)
        assert field.table.abs().max() <= 1e-4  # near zero, as Instant-NGP starts
        assert "table" in field.state_dict() and "offsets" not in field.state_dict()

    def test_encode_is_the_trilinear_reference(self):
        field = GridRadianceField(GridFieldConfig(levels=2, min_resolution=4, max_resolution=8))
        with torch.no_grad():
            field.table.normal_()
        positions = torch.rand(64, 3) * 2 - 1
        torch.testing.assert_close(
            field.encode(positions), grid_encode_reference(positions, field.table, field.resolutions, field.offsets)
        )

    def test_shapes_and_gradients_reach_every_level(self):
        field = GridRadianceField(GridFieldConfig(levels=2, min_resolution=4, max_resolution=8, hidden_width=16))
        directions = torch.nn.functional.normalize(torch.randn(40, 3), dim=-1)
        density, raw_color = field(torch.rand(40, 3) * 2 - 1, directions)
        assert density.shape == (40,) and raw_color.shape == (40, 3)
        (density.sum() + raw_color.sum()).backward()
        for offset, resolution in zip(field.offsets.tolist(), field.resolutions.tolist()):
            assert field.table.grad[offset : offset + resolution**3].abs().sum() > 0
        assert field.density(torch.zeros(3, 3)).shape == (3,)


class TestOccupancyGrid:
    def test_starts_all_occupied_and_unfilled(self):
        grid = OccupancyGrid(8)
        assert not grid.filled
        assert grid.occupied.all() and grid.occupied.shape == (8, 8, 8)

    def test_cell_centres_follow_the_zyx_layout(self):
        centers = OccupancyGrid(4).cell_centers().reshape(4, 4, 4, 3)
        torch.testing.assert_close(centers[1, 2, 3], torch.tensor([0.75, 0.25, -0.25]))

    def test_update_marks_dense_cells(self):
        grid = OccupancyGrid(16)
        grid.update(lambda p: 10.0 * (p.norm(dim=-1) < 0.5).float(), decay=0.9, threshold=1.0)
        assert grid.filled
        assert grid.occupied[8, 8, 8] and not grid.occupied[0, 0, 0]
        # Cells wholly inside the ball are occupied, cells wholly outside are not.
        centers = grid.cell_centers()
        half_diagonal = 3**0.5 / 16
        inside = centers.norm(dim=-1) < 0.5 - half_diagonal
        outside = centers.norm(dim=-1) > 0.5 + half_diagonal
        assert grid.occupied.reshape(-1)[inside].all() and not grid.occupied.reshape(-1)[outside].any()

    def test_threshold_falls_to_the_mean_of_a_faint_field(self):
        # An untrained field is faint everywhere: cells above its mean stay occupied, not none.
        grid = OccupancyGrid(8)
        grid.update(lambda p: 0.01 * (1.0 + p[:, 0]), decay=0.9, threshold=5.0)
        fraction = grid.occupied.float().mean()
        assert 0.3 < fraction < 0.7

    def test_decay_forgets_slowly(self):
        grid = OccupancyGrid(4)
        grid.update(lambda p: torch.full(p.shape[:1], 2.0), decay=0.5, threshold=1.5)
        grid.update(lambda p: torch.zeros(p.shape[0]), decay=0.5, threshold=1.5)
        torch.testing.assert_close(grid.densities, torch.full_like(grid.densities, 1.0))
        assert not grid.occupied.any()

    def test_partial_update_refreshes_a_quarter_plus_occupied_cells(self):
        grid = OccupancyGrid(8)
        grid.update(lambda p: 10.0 * (p[:, 0] > 0.5).float(), decay=1.0, threshold=1.0)
        seen = []
        grid.update(lambda p: seen.append(p) or torch.zeros(p.shape[0]), decay=1.0, threshold=1.0, all_cells=False)
        evaluated = torch.cat(seen)
        assert evaluated.shape[0] < 512 // 2 + 128 + 1
        assert (evaluated[:, 0] > 0.5).sum() >= 128  # every occupied cell (x > 0.5: 2 of 8 layers) is refreshed
