"""Radiance fields: position (in the normalised scene box) + direction -> density, raw colour.

Positions are normalised so the scene box's longest side spans [-1, 1]; densities are per
unit of that normalised length, which makes the hyper-parameters independent of scene scale.
Raw colours are pre-activation: the backbone's LDR colour is sigmoid(raw) (paper field) or the
grid field's `color_activation` of it.
"""

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from backbones.nerf.config import DensityActivation, GridFieldConfig, MlpFieldConfig
from backbones.nerf.kernels import grid_encode


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


# exp's input is capped here: exp(20) ~ 5e8 is opaque over any sample, and stays finite.
MAX_LOG_DENSITY = 20.0


def activate_density(raw: Tensor, activation: DensityActivation) -> Tensor:
    """Non-negative, finite density from a raw network output: [...] -> [...]."""
    if activation == "relu":
        return F.relu(raw)
    if activation == "exp":
        return torch.exp(raw.clamp(max=MAX_LOG_DENSITY))
    return F.softplus(raw)


def bounded_logit(logit: Tensor, bound: float) -> Tensor:
    """bound * tanh(logit / bound): the logit where it is small against the bound, never beyond it
    (bound 0: the logit unchanged). What L2H-CC reads per sample (GridFieldConfig.l2h_input_bound)."""
    return logit if bound == 0 else bound * torch.tanh(logit / bound)


class MlpRadianceField(nn.Module):
    """The official NeRF MLP: depth x width ReLU layers with one skip, view-dependent colour head."""

    def __init__(self, config: MlpFieldConfig):
        super().__init__()
        self.config = config
        xyz_size, dir_size = encoded_size(config.xyz_frequencies), encoded_size(config.dir_frequencies)
        self.position_layers = nn.ModuleList(
            [nn.Linear(xyz_size, config.width)]
            + [
                nn.Linear(config.width + (xyz_size if index == config.skip_layer + 1 else 0), config.width)
                for index in range(1, config.depth)
            ]
        )
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
        view_input = torch.cat(
            [self.feature_head(hidden), positional_encoding(directions, self.config.dir_frequencies)], dim=-1
        )
        raw_color = self.color_head(F.relu(self.view_layer(view_input)))
        return density, raw_color


def grid_resolutions(config: GridFieldConfig) -> list[int]:
    """Vertices per side of each level, geometric from min_resolution to max_resolution."""
    if config.levels == 1:
        return [config.max_resolution]
    growth = (config.max_resolution / config.min_resolution) ** (1.0 / (config.levels - 1))
    return [round(config.min_resolution * growth**level) for level in range(config.levels)]


class GridRadianceField(nn.Module):
    """Multi-resolution dense feature grids (one table, C++ trilinear kernel), a tiny density MLP
    and a tiny colour MLP."""

    resolutions: Tensor  # buffers, for the type checker (nn.Module.__getattr__ returns Tensor | Module)
    offsets: Tensor

    def __init__(self, config: GridFieldConfig):
        super().__init__()
        self.config = config
        resolutions = grid_resolutions(config)
        if min(resolutions) < 2:
            raise ValueError(f"GridFieldConfig needs min_resolution >= 2, got resolutions {resolutions}")
        sizes = torch.tensor([r**3 for r in resolutions])
        self.register_buffer("resolutions", torch.tensor(resolutions), persistent=False)
        self.register_buffer("offsets", torch.cumsum(sizes, 0) - sizes, persistent=False)
        # Near-zero features, as Instant-NGP initialises its tables: the MLPs start from biases.
        self.table = nn.Parameter(torch.empty(int(sizes.sum()), config.features_per_level).uniform_(-1e-4, 1e-4))
        width = config.hidden_width
        self.density_mlp = nn.Sequential(
            nn.Linear(config.levels * config.features_per_level, width),
            nn.ReLU(),
            nn.Linear(width, 1 + config.geo_features),
        )
        self.color_mlp = nn.Sequential(
            nn.Linear(config.geo_features + encoded_size(config.dir_frequencies), width), nn.ReLU(), nn.Linear(width, 3)
        )

    def encode(self, positions: Tensor) -> Tensor:
        """positions: [M, 3] in [-1, 1]. Returns grid features [M, levels * features_per_level]."""
        return grid_encode(positions, self.table, self.resolutions, self.offsets)

    def density_and_geometry(self, positions: Tensor) -> tuple[Tensor, Tensor]:
        """positions: [M, 3] in [-1, 1]. Returns density [M] and geometry features [M, geo_features]."""
        out = self.density_mlp(self.encode(positions))
        config = self.config
        density = config.density_scale * activate_density(out[:, 0] + config.density_bias, config.density_activation)
        return density, out[:, 1:]

    def density(self, positions: Tensor) -> Tensor:
        """positions: [M, 3] in [-1, 1]. Returns density [M] (for the occupancy grid)."""
        return self.density_and_geometry(positions)[0]

    def color(self, geometry: Tensor, directions: Tensor) -> Tensor:
        """geometry: [M, geo_features]; directions: [M, 3] unit. Returns raw (pre-activation) colour [M, 3]."""
        return self.color_mlp(torch.cat([geometry, positional_encoding(directions, self.config.dir_frequencies)], -1))

    def forward(self, positions: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """positions: [M, 3] in [-1, 1]; directions: [M, 3] unit. Returns density [M], raw colour [M, 3]."""
        density, geometry = self.density_and_geometry(positions)
        return density, self.color(geometry, directions)


class OccupancyGrid(nn.Module):
    """Which cells of the normalised cube [-1, 1]^3 may hold anything: samples go only there.

    A cell is occupied when its cached density is above a threshold. The cache keeps, per cell,
    max(decay * old, density at a random point of the cell), refreshed from the field during
    training (Instant-NGP, nerfacc). Cells no training camera sees are never occupied. Until the
    first refresh every seen cell is occupied, so an untrained field renders with plain
    stratified samples.
    """

    densities: Tensor  # buffers, for the type checker (nn.Module.__getattr__ returns Tensor | Module)
    seen: Tensor
    occupied: Tensor
    updates: Tensor

    def __init__(self, resolution: int):
        super().__init__()
        if resolution < 1:
            raise ValueError(f"occupancy_resolution must be >= 1, got {resolution}")
        self.resolution = resolution
        shape = (resolution, resolution, resolution)  # [z, y, x]
        self.register_buffer("densities", torch.zeros(shape))
        self.register_buffer("seen", torch.ones(shape, dtype=torch.bool))
        self.register_buffer("occupied", torch.ones(shape, dtype=torch.bool))
        self.register_buffer("updates", torch.zeros((), dtype=torch.long))

    @property
    def filled(self) -> bool:
        return bool(self.updates > 0)

    def cell_centers(self) -> Tensor:
        """[G^3, 3] (x, y, z) centres of the cells, in the order of the flattened [z, y, x] grid."""
        axis = -1.0 + (2.0 * torch.arange(self.resolution, dtype=torch.float32) + 1.0) / self.resolution
        z, y, x = torch.meshgrid(axis, axis, axis, indexing="ij")
        return torch.stack([x, y, z], dim=-1).reshape(-1, 3)

    def lookup(self, positions: Tensor) -> Tensor:
        """Cached density, trilinear between cell centres. positions: [M, 3] in [-1, 1]. Returns [M]."""
        grid = self.densities.reshape(1, 1, *self.densities.shape)
        values = F.grid_sample(
            grid,
            positions.reshape(1, 1, 1, -1, 3).to(grid.dtype),
            mode="bilinear",
            padding_mode="border",
            align_corners=False,
        )
        return values.reshape(-1)

    def occupied_at(self, positions: Tensor) -> Tensor:
        """Whether the cells holding positions [..., 3] (in [-1, 1], clamped to the cube) are occupied: bool [...]."""
        cells = ((positions + 1.0) * (self.resolution / 2.0)).floor().long().clamp(0, self.resolution - 1)
        return self.occupied[cells[..., 2], cells[..., 1], cells[..., 0]]

    @torch.no_grad()
    def mark_seen(self, cameras, to_world) -> None:
        """Keep only cells some camera sees: a cell counts as seen when a corner or its centre
        projects into an image in front of the camera; the result grows by one cell on every
        side, so cells that cross an image border are kept too.

        cameras: the training cameras; to_world: normalised positions [M, 3] -> world [M, 3].
        """
        half = 1.0 / self.resolution
        offsets = torch.tensor(
            [[0.0, 0.0, 0.0]]
            + [[sx * half, sy * half, sz * half] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
        )
        centers = self.cell_centers()
        seen = torch.zeros(centers.shape[0], dtype=torch.bool)
        for offset in offsets:
            points = to_world(centers + offset)
            for camera in cameras:
                pixels, depth = camera.project(points)
                seen |= (
                    (depth > camera.near)
                    & (pixels[:, 0] >= 0)
                    & (pixels[:, 0] <= camera.width)
                    & (pixels[:, 1] >= 0)
                    & (pixels[:, 1] <= camera.height)
                )
        grid = seen.reshape(1, 1, *self.seen.shape).float()
        self.seen.copy_(F.max_pool3d(grid, 3, stride=1, padding=1)[0, 0] > 0)
        self.occupied &= self.seen

    @torch.no_grad()
    def update(self, density_fn, decay: float, threshold: float, all_cells: bool = True, chunk: int = 65536) -> None:
        """Refresh cells with density_fn at a random point of each: new = max(decay * old, fresh).

        density_fn: positions [M, 3] in [-1, 1] -> densities [M] (per unit of normalised length).
        threshold: a density; a cell is occupied above min(threshold, mean density of seen cells).
        all_cells: refresh every seen cell; otherwise a random quarter of the cells plus the
        occupied ones (Instant-NGP after its warm-up).
        """
        size = self.resolution
        seen = self.seen.reshape(-1)
        if all_cells:
            chosen = seen.nonzero()[:, 0]
        else:
            count = max(1, seen.numel() // 4)
            candidates = torch.cat([torch.randint(seen.numel(), (count,)), self.occupied.reshape(-1).nonzero()[:, 0]])
            chosen = candidates[seen[candidates]].unique()
        cells = self.cell_centers()[chosen]
        positions = (cells + (torch.rand_like(cells) - 0.5) * (2.0 / size)).clamp(-1.0, 1.0)
        fresh = torch.cat([density_fn(part) for part in positions.split(chunk)]) if len(positions) else cells[:, 0]
        cache = self.densities.reshape(-1)
        old = cache[chosen] * decay if self.filled else torch.zeros_like(fresh)
        cache[chosen] = torch.maximum(old, fresh)
        mean = cache[seen].mean() if seen.any() else cache.new_zeros(())
        self.occupied.copy_((self.densities > torch.clamp(mean, max=threshold)) & self.seen)
        self.updates += 1
