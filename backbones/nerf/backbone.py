"""NerfBackbone: rays from the project's cameras, sampling, a field, and the compositing closure.

The backbone hands out per-sample LDR colours [N_rays, S, 3] and a closure that composites any
per-sample values with the same volume-rendering weights, so a method lifts every sample to
HDR (L2H-CC) and renders LDR and HDR in one pass, as the official Mono-HDR-NeRF code does.
"""

import torch
from torch import Tensor

from backbones.nerf.config import NerfConfig
from backbones.nerf.fields import DensityGrid, GridRadianceField, MlpRadianceField
from backbones.nerf.rendering import compositing_weights, make_composite, make_packed_composite, sample_deltas
from backbones.nerf.sampling import ray_segments, sample_pdf, sample_stratified
from mono_hdr_plugin.backbone import Backbone, LdrFeatures, SceneInfo
from mono_hdr_plugin.cameras import Camera


class NerfBackbone(Backbone):
    """Neural radiance field with the official MLP (field=paper) or a fast grid field (field=fast).

    Instance attributes the trainer and evaluator read:
        pixel_batch: rays per training step (the active field's rays_per_step).
        render_chunk: rays per piece when rendering a whole image (split camera.pixels).
    """

    config_class = NerfConfig
    loss_kind = "mse"
    paper_backbone = "NeRF"
    pixel_batch = 1024

    def __init__(self, config: NerfConfig, scene: SceneInfo):
        super().__init__(config, scene)
        bounds_min = torch.as_tensor(scene.bounds_min, dtype=torch.float32).reshape(-1)
        bounds_max = torch.as_tensor(scene.bounds_max, dtype=torch.float32).reshape(-1)
        if bounds_min.shape != (3,) or bounds_max.shape != (3,) or not (
                torch.isfinite(bounds_min).all() and torch.isfinite(bounds_max).all()
                and (bounds_max > bounds_min).all()):
            raise ValueError(f"SceneInfo.bounds_min/bounds_max must be finite 3-vectors with max > min, "
                             f"got {scene.bounds_min} and {scene.bounds_max}; fix the scene's bounds")
        if len(config.background) != 3:
            raise ValueError(f"NerfConfig.background must be 3 numbers (RGB), got {config.background}")
        self.register_buffer("bounds_min", bounds_min)
        self.register_buffer("bounds_max", bounds_max)
        self.register_buffer("background", torch.tensor(config.background, dtype=torch.float32))
        # One isotropic scale (half the longest side) so normalised distances stay Euclidean.
        self.scene_center = 0.5 * (bounds_min + bounds_max)
        self.scene_scale = float(0.5 * (bounds_max - bounds_min).max())
        self.render_chunk = config.render_chunk
        if config.field == "paper":
            paper = config.paper
            if paper.coarse_samples < 3 or paper.fine_samples < 1:
                raise ValueError("NerfConfig.paper needs coarse_samples >= 3 and fine_samples >= 1, "
                                 f"got {paper.coarse_samples} and {paper.fine_samples}")
            self.coarse_field = MlpRadianceField(paper)
            self.fine_field = MlpRadianceField(paper)
            self.pixel_batch = paper.rays_per_step
        elif config.field == "fast":
            fast = config.fast
            if fast.uniform_samples < 1 or fast.importance_samples < 0 or fast.proposal_samples < 1:
                raise ValueError("NerfConfig.fast needs uniform_samples >= 1, importance_samples >= 0 "
                                 f"and proposal_samples >= 1, got {fast.uniform_samples}, "
                                 f"{fast.importance_samples}, {fast.proposal_samples}")
            self.grid_field = GridRadianceField(fast)
            self.density_grid = DensityGrid(fast.density_grid_resolution)
            self.pixel_batch = fast.rays_per_step
        else:
            raise ValueError(f"NerfConfig.field must be 'paper' or 'fast', got {config.field!r}")

    @classmethod
    def presets(cls) -> dict[str, NerfConfig]:
        """fast: grid field with density-grid sampling (CPU default); paper: the official MLP recipe."""
        return {"fast": NerfConfig(field="fast"), "paper": NerfConfig(field="paper")}

    def parameter_groups(self) -> list[dict]:
        if self.config.field == "paper":
            return [{"name": "nerf_mlp", "params": list(self.coarse_field.parameters())
                     + list(self.fine_field.parameters()), "lr": self.config.paper.lr}]
        field = self.grid_field
        return [{"name": "nerf_grid", "params": list(field.grids.parameters()), "lr": self.config.fast.grid_lr},
                {"name": "nerf_mlp", "params": list(field.density_mlp.parameters())
                 + list(field.color_mlp.parameters()), "lr": self.config.fast.mlp_lr}]

    def learning_rate(self, group_name: str, step: int, base_lr: float) -> float:
        """paper: NeRF's lr * factor ** (step / decay_steps); fast: decays to lr_final_factor over the run."""
        if self.config.field == "paper":
            paper = self.config.paper
            return base_lr * paper.lr_decay_factor ** (step / paper.lr_decay_steps)
        return base_lr * self.config.fast.lr_final_factor ** (step / max(self.max_steps, 1))

    def after_step(self, step: int, features: LdrFeatures, optimizer: torch.optim.Optimizer) -> None:
        """fast: refresh the density grid every density_grid_update_every steps (from step 0)."""
        fast = self.config.fast
        if self.config.field == "fast" and step % fast.density_grid_update_every == 0:
            self.density_grid.update(self.grid_field.density, fast.density_grid_decay)

    @property
    def stochastic_sampling(self) -> bool:
        """Jitter samples only while training with gradients: evaluation, even in train mode
        under torch.no_grad, renders deterministically, so chunked and whole renders agree."""
        return self.training and torch.is_grad_enabled()

    def normalise(self, points: Tensor) -> Tensor:
        """World points [..., 3] -> the field's frame, where the box's longest side spans [-1, 1]."""
        return (points - self.scene_center.to(points)) / self.scene_scale

    def render_ldr_features(self, camera: Camera) -> LdrFeatures:
        """Per-sample LDR colours of the camera's rays and their compositing closure.

        Returns LdrFeatures with colors, raw_colors [N_rays, S, 3] (N_rays = prod(output_shape)) and
        composite: [N_rays, S, C] -> [*camera.output_shape, C] for field=paper; for field=fast the
        samples are packed, colors [M, 3] and composite [M, C] -> [*output_shape, C], holding only
        the M samples that contribute (extras "ray_indices" [M] says whose they are). Extras "weights"
        and "sample_distances" (t along the unit ray) [N_rays, S],
        "depth" (expected distance, 0 where empty) and "alpha" (accumulation) [*output_shape],
        and for field=paper auxiliary = [the coarse network's LdrFeatures].
        """
        origins, directions = camera.rays()
        device = self.bounds_min.device
        origins, directions = origins.reshape(-1, 3).to(device), directions.reshape(-1, 3).to(device)
        output_shape = camera.output_shape
        render = self._render_paper if self.config.field == "paper" else self._render_fast
        return render(origins, directions, camera, output_shape, self.stochastic_sampling)

    def _features(self, density: Tensor, raw_color: Tensor, t: Tensor, t_far: Tensor,
                  output_shape: tuple[int, ...]) -> LdrFeatures:
        weights = compositing_weights(density, sample_deltas(t, t_far) / self.scene_scale)
        extras = {"weights": weights, "sample_distances": t,
                  "depth": (weights * t).sum(dim=-1).reshape(output_shape),
                  "alpha": weights.sum(dim=-1).reshape(output_shape)}
        return LdrFeatures(colors=torch.sigmoid(raw_color), raw_colors=raw_color,
                           composite=make_composite(weights, output_shape, self.background), extras=extras)

    def _query(self, field, origins: Tensor, directions: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """Field at every sample: density [N, S], raw colour [N, S, 3]."""
        positions = self.normalise(origins[:, None] + t[..., None] * directions[:, None])
        rays, samples = t.shape
        density, raw_color = field(positions.reshape(-1, 3),
                                   directions[:, None].expand(rays, samples, 3).reshape(-1, 3))
        return density.reshape(rays, samples), raw_color.reshape(rays, samples, 3)

    def _render_paper(self, origins: Tensor, directions: Tensor, camera: Camera,
                      output_shape: tuple[int, ...], stochastic: bool) -> LdrFeatures:
        paper = self.config.paper
        bounds = (self.bounds_min, self.bounds_max) if paper.clip_to_bounds else None
        t_near, t_far = ray_segments(origins, directions, camera.near, camera.far, bounds)
        t_coarse = sample_stratified(t_near, t_far, paper.coarse_samples, perturb=stochastic)
        coarse = self._features(*self._query(self.coarse_field, origins, directions, t_coarse),
                                t_coarse, t_far, output_shape)
        # NeRF's importance sampling: bins between coarse samples, interior weights, no gradient.
        with torch.no_grad():
            mids = 0.5 * (t_coarse[:, 1:] + t_coarse[:, :-1])
            t_importance = sample_pdf(mids, coarse.extras["weights"][:, 1:-1].detach(), paper.fine_samples,
                                      deterministic=not stochastic)
            t_fine = torch.sort(torch.cat([t_coarse, t_importance], dim=-1), dim=-1).values
        fine = self._features(*self._query(self.fine_field, origins, directions, t_fine), t_fine, t_far,
                              output_shape)
        fine.auxiliary = [coarse]
        return fine

    def _render_fast(self, origins: Tensor, directions: Tensor, camera: Camera,
                     output_shape: tuple[int, ...], stochastic: bool) -> LdrFeatures:
        """Packed features: only samples in occupied cells get a density, and only those whose
        weight reaches min_sample_weight get a colour (colors [M, 3], composite [M, C] -> image)."""
        fast = self.config.fast
        t_near, t_far = ray_segments(origins, directions, camera.near, camera.far,
                                     (self.bounds_min, self.bounds_max))
        t = sample_stratified(t_near, t_far, fast.uniform_samples, perturb=stochastic)
        if fast.importance_samples > 0:
            with torch.no_grad():
                t_importance = self._proposal_samples(origins, directions, t_near, t_far, stochastic)
            t = torch.sort(torch.cat([t, t_importance], dim=-1), dim=-1).values
        positions = self.normalise(origins[:, None] + t[..., None] * directions[:, None]).reshape(-1, 3)
        occupied = self._occupied(positions).nonzero()[:, 0]
        density_occupied, geometry = self.grid_field.density_and_geometry(positions[occupied])
        density = positions.new_zeros(positions.shape[0]).index_put((occupied,), density_occupied)
        weights = compositing_weights(density.reshape(t.shape), sample_deltas(t, t_far) / self.scene_scale)
        flat_weights = weights.reshape(-1)
        kept = (flat_weights.detach() >= max(fast.min_sample_weight, torch.finfo(weights.dtype).tiny)).nonzero()[:, 0]
        # Every kept sample has a positive weight, hence a positive density: it is among the occupied ones.
        rank_in_occupied = torch.full_like(density, -1, dtype=torch.long).index_put(
            (occupied,), torch.arange(occupied.shape[0], device=occupied.device))
        ray_indices = kept // t.shape[1]
        raw_color = self.grid_field.color(geometry[rank_in_occupied[kept]], directions[ray_indices])
        accumulation = weights.sum(dim=-1)
        extras = {"weights": weights, "sample_distances": t, "ray_indices": ray_indices,
                  "depth": (weights * t).sum(dim=-1).reshape(output_shape),
                  "alpha": accumulation.reshape(output_shape)}
        composite = make_packed_composite(flat_weights[kept], ray_indices, accumulation, output_shape,
                                          self.background)
        return LdrFeatures(colors=torch.sigmoid(raw_color), raw_colors=raw_color, composite=composite,
                           extras=extras)

    def _proposal_samples(self, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
                          stochastic: bool) -> Tensor:
        """Importance samples [N, importance_samples] from the density grid's rendering weights."""
        fast = self.config.fast
        edges = sample_stratified(t_near, t_far, fast.proposal_samples + 1, perturb=False)
        mids = 0.5 * (edges[:, 1:] + edges[:, :-1])
        positions = self.normalise(origins[:, None] + mids[..., None] * directions[:, None])
        cached = self.density_grid.lookup(positions.reshape(-1, 3)).reshape(mids.shape)
        weights = compositing_weights(cached, (edges[:, 1:] - edges[:, :-1]) / self.scene_scale)
        return sample_pdf(edges, weights, fast.importance_samples, deterministic=not stochastic)

    def _occupied(self, positions: Tensor) -> Tensor:
        """Which normalised positions [M, 3] the field must evaluate: [M] bool."""
        # Samples of rays that miss the box sit outside the grids' cube [-1, 1]^3: never evaluated.
        # The tolerance keeps samples on the box faces that rounding pushed just outside.
        wanted = (positions.abs() <= 1.0 + 1e-4).all(dim=-1)
        if self.density_grid.filled:
            wanted &= self.density_grid.lookup(positions) > self.config.fast.occupancy_threshold
        return wanted
