"""Radiance fields: position (in the normalised scene box) + direction -> density, raw colour.

Positions are normalised so the scene box's longest side spans [-1, 1]; densities are per
unit of that normalised length, which makes the hyper-parameters independent of scene scale.
Raw colours are pre-sigmoid: the backbone's LDR colour is sigmoid(raw).
"""

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from backbones.nerf.config import DensityActivation, GridFieldConfig, MlpFieldConfig


def positional_encoding(x: Tensor, num_frequencies: int) -> Tensor:
    """NeRF's encoding [x, sin(2^k x), cos(2^k x) for k < num_frequencies].

    x: [..., D]. Returns [..., D * (1 + 2 * num_frequencies)].
    """
    frequencies = 2.0 ** torch.arange(num_frequencies, dtype=x.dtype, device=x.device)
    scaled = x[..., None, :] * frequencies[:, None]
    periodic = torch.stack([torch.sin(scaled), torch.cos(scaled)], dim=-2)
    return torch.cat([x, periodic.flatten(start_dim=-3)], dim=-1)


def encoded_size(num_frequencies: int, dims: int = 3) -> int:
    """Channels of positional_encoding for `dims`-dimensional input."""
    return dims * (1 + 2 * num_frequencies)


def activate_density(raw: Tensor, activation: DensityActivation) -> Tensor:
    """Non-negative, finite density from a raw network output: [...] -> [...]."""
    return F.relu(raw) if activation == "relu" else F.softplus(raw)


class MlpRadianceField(nn.Module):
    """The official NeRF MLP: depth x width ReLU layers with one skip, view-dependent colour head."""

    def __init__(self, config: MlpFieldConfig):
        super().__init__()
        self.config = config
        xyz_size, dir_size = encoded_size(config.xyz_frequencies), encoded_size(config.dir_frequencies)
        self.position_layers = nn.ModuleList(
            [nn.Linear(xyz_size, config.width)]
            + [nn.Linear(config.width + (xyz_size if index == config.skip_layer + 1 else 0), config.width)
               for index in range(1, config.depth)])
        self.density_head = nn.Linear(config.width, 1)
        self.feature_head = nn.Linear(config.width, config.width)
        self.view_layer = nn.Linear(config.width + dir_size, config.width // 2)
        self.color_head = nn.Linear(config.width // 2, 3)

    def forward(self, positions: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """positions: [M, 3] normalised; directions: [M, 3] unit. Returns density [M], raw colour [M, 3]."""
        encoded = positional_encoding(positions, self.config.xyz_frequencies)
        hidden = encoded
        for index, layer in enumerate(self.position_layers):
            hidden = F.relu(layer(hidden))
            if index == self.config.skip_layer:
                hidden = torch.cat([encoded, hidden], dim=-1)
        density = activate_density(self.density_head(hidden)[:, 0], self.config.density_activation)
        view_input = torch.cat([self.feature_head(hidden),
                                positional_encoding(directions, self.config.dir_frequencies)], dim=-1)
        raw_color = self.color_head(F.relu(self.view_layer(view_input)))
        return density, raw_color


def grid_resolutions(config: GridFieldConfig) -> list[int]:
    """Vertices per side of each level, geometric from min_resolution to max_resolution."""
    if config.levels == 1:
        return [config.max_resolution]
    growth = (config.max_resolution / config.min_resolution) ** (1.0 / (config.levels - 1))
    return [round(config.min_resolution * growth ** level) for level in range(config.levels)]


def sample_grid(grid: Tensor, positions: Tensor) -> Tensor:
    """Trilinear look-up. grid: [1, C, R, R, R]; positions: [M, 3] in [-1, 1]. Returns [M, C]."""
    coordinates = positions.reshape(1, 1, 1, -1, 3).to(grid.dtype)
    values = F.grid_sample(grid, coordinates, mode="bilinear", padding_mode="border", align_corners=True)
    return values.reshape(grid.shape[1], -1).T


class GridRadianceField(nn.Module):
    """Multi-resolution dense feature grids, a tiny density MLP and a tiny colour MLP."""

    def __init__(self, config: GridFieldConfig):
        super().__init__()
        self.config = config
        # Near-zero features, as Instant-NGP initialises its tables: the MLPs start from biases.
        self.grids = nn.ParameterList([
            nn.Parameter(torch.empty(1, config.features_per_level, size, size, size).uniform_(-1e-4, 1e-4))
            for size in grid_resolutions(config)])
        width = config.hidden_width
        self.density_mlp = nn.Sequential(nn.Linear(config.levels * config.features_per_level, width),
                                         nn.ReLU(), nn.Linear(width, 1 + config.geo_features))
        self.color_mlp = nn.Sequential(
            nn.Linear(config.geo_features + encoded_size(config.dir_frequencies), width), nn.ReLU(),
            nn.Linear(width, 3))

    def encode(self, positions: Tensor) -> Tensor:
        """positions: [M, 3] in [-1, 1]. Returns grid features [M, levels * features_per_level]."""
        return torch.cat([sample_grid(grid, positions) for grid in self.grids], dim=-1)

    def density_and_geometry(self, positions: Tensor) -> tuple[Tensor, Tensor]:
        """positions: [M, 3] in [-1, 1]. Returns density [M] and geometry features [M, geo_features]."""
        out = self.density_mlp(self.encode(positions))
        config = self.config
        density = config.density_scale * activate_density(out[:, 0] + config.density_bias, config.density_activation)
        return density, out[:, 1:]

    def density(self, positions: Tensor) -> Tensor:
        """positions: [M, 3] in [-1, 1]. Returns density [M] (for the density grid)."""
        return self.density_and_geometry(positions)[0]

    def color(self, geometry: Tensor, directions: Tensor) -> Tensor:
        """geometry: [M, geo_features]; directions: [M, 3] unit. Returns raw (pre-sigmoid) colour [M, 3]."""
        return self.color_mlp(torch.cat([geometry, positional_encoding(directions, self.config.dir_frequencies)], -1))

    def forward(self, positions: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """positions: [M, 3] in [-1, 1]; directions: [M, 3] unit. Returns density [M], raw colour [M, 3]."""
        density, geometry = self.density_and_geometry(positions)
        return density, self.color(geometry, directions)


class DensityGrid(nn.Module):
    """A coarse cache of the field's density over the normalised box [-1, 1]^3.

    It decides which samples to skip (occupancy) and where to put importance samples
    (proposal). Until the first `update`, every cell counts as occupied and the proposal is
    uniform, so an untrained model renders with plain stratified sampling.
    """

    def __init__(self, resolution: int):
        super().__init__()
        self.resolution = resolution
        self.register_buffer("densities", torch.zeros(1, 1, resolution, resolution, resolution))
        self.register_buffer("updates", torch.zeros((), dtype=torch.long))

    @property
    def filled(self) -> bool:
        return bool(self.updates > 0)

    def lookup(self, positions: Tensor) -> Tensor:
        """Trilinear cached density. positions: [M, 3] in [-1, 1]. Returns [M]."""
        return sample_grid(self.densities, positions)[:, 0]

    @torch.no_grad()
    def update(self, density_fn, decay: float, chunk: int = 65536) -> None:
        """Refresh every cell with density_fn at a random point of the cell: new = max(decay * old, fresh).

        density_fn: positions [M, 3] in [-1, 1] -> densities [M].
        """
        size = self.resolution
        axis = torch.arange(size, dtype=torch.float32, device=self.densities.device)
        # grid_sample reads the last axis of `positions` as x = the grid's last dimension.
        z, y, x = torch.meshgrid(axis, axis, axis, indexing="ij")
        cells = torch.stack([x, y, z], dim=-1).reshape(-1, 3)
        # Vertices sit at -1 + 2 i / (size - 1) (align_corners=True): jitter half a cell around them.
        positions = (-1.0 + 2.0 * (cells + torch.rand_like(cells) - 0.5) / (size - 1)).clamp(-1.0, 1.0)
        fresh = torch.cat([density_fn(part) for part in positions.split(chunk)])
        current = self.densities.reshape(-1)
        current.copy_(torch.maximum(current * decay if self.filled else torch.zeros_like(current), fresh))
        self.updates += 1
