"""NerfBackbone: rays from the project's cameras, sampling, a field, and the compositing closure.

The backbone hands out per-sample LDR colours and a closure that composites any per-sample
values with the same volume-rendering weights, so a method lifts every sample to HDR (L2H-CC)
and renders LDR and HDR in one pass, as the official Mono-HDR-NeRF code does.
"""

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from backbones.nerf._extension import load_extension
from backbones.nerf.config import GridFieldConfig, MlpFieldConfig, NerfConfig
from backbones.nerf.fields import GridRadianceField, MlpRadianceField, OccupancyGrid, bounded_logit
from backbones.nerf.kernels import march_rays
from backbones.nerf.rendering import compositing_weights, make_composite, make_packed_composite, sample_deltas
from backbones.nerf.sampling import ray_segments, resample_occupied, sample_pdf, sample_stratified
from backbones.nerf.unbounded import (
    camera_region,
    contract,
    contracted_lengths,
    far_candidates,
    uncontract,
    unwarp,
)
from mono_hdr_plugin.core.backbone import Backbone, LdrFeatures, SceneInfo
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.core.environment import EnvironmentMap, up_from_cameras


def _checked_bounds(scene: SceneInfo) -> tuple[Tensor, Tensor]:
    """The scene's bounds as float 3-vectors; they must be finite with max > min."""
    bounds_min = torch.as_tensor(scene.bounds_min, dtype=torch.float32).reshape(-1)
    bounds_max = torch.as_tensor(scene.bounds_max, dtype=torch.float32).reshape(-1)
    if (
        bounds_min.shape != (3,)
        or bounds_max.shape != (3,)
        or not (
            torch.isfinite(bounds_min).all() and torch.isfinite(bounds_max).all() and (bounds_max > bounds_min).all()
        )
    ):
        raise ValueError(
            f"SceneInfo.bounds_min/bounds_max must be finite 3-vectors with max > min, "
            f"got {scene.bounds_min} and {scene.bounds_max}; fix the scene's bounds"
        )
    return bounds_min, bounds_max


def unbounded_choices(config: NerfConfig, unbounded: bool) -> tuple[bool, bool]:
    """(contracted, environment background) for a scene: the flags, where auto follows the scene."""
    grid = isinstance(config.field, GridFieldConfig)
    if not grid and (config.contraction == "on" or config.background == "environment"):
        raise ValueError(
            "--backbone.contraction on and --backbone.background environment need the grid field: "
            "use --preset cpu, or set them to off / none with --preset paper"
        )
    contracted = config.contraction == "on" or (config.contraction == "auto" and unbounded and grid)
    environment = config.background == "environment" or (config.background == "auto" and unbounded and grid)
    return contracted, environment


def _environment_map(scene: SceneInfo, width: int) -> EnvironmentMap:
    """The background at infinity, its pole the cameras' mean up direction, as many pyramid levels
    (up to 4) as leave 4 texels at the coarsest."""
    cameras = scene.train_cameras
    up = up_from_cameras(torch.stack([c.c2w.float() for c in cameras])) if cameras else torch.tensor([0.0, 0.0, 1.0])
    levels = next(n for n in (4, 3, 2, 1) if width >> (2 * (n - 1)) >= 4)
    return EnvironmentMap(up, width=width, levels=levels)


class NerfBackbone(Backbone):
    """Neural radiance field: a grid field made for a CPU (preset cpu) or the official MLP (preset paper).

    Instance attributes the trainer and evaluator read:
        pixel_batch: rays of the next training step (paper: fixed; cpu: sized to samples_per_step).
        render_chunk: rays per piece when rendering a whole image (split camera.pixels).
    """

    config_class = NerfConfig
    loss_kind = "mse"
    paper_backbone = "NeRF"
    pixel_batch = 1024
    bounds_min: Tensor  # buffers, for the type checker (nn.Module.__getattr__ returns Tensor | Module)
    bounds_max: Tensor
    background: Tensor
    rays_per_step: Tensor  # the grid field's only

    def __init__(self, config: NerfConfig, scene: SceneInfo):
        super().__init__(config, scene)
        bounds_min, bounds_max = _checked_bounds(scene)
        if len(config.background_color) != 3:
            raise ValueError(f"NerfConfig.background_color must be 3 numbers (RGB), got {config.background_color}")
        if config.render_chunk < 1:
            raise ValueError(f"NerfConfig.render_chunk must be >= 1, got {config.render_chunk}")
        self.register_buffer("bounds_min", bounds_min)
        self.register_buffer("bounds_max", bounds_max)
        # "background" is the name checkpoints hold the colour under.
        self.register_buffer("background", torch.tensor(config.background_color, dtype=torch.float32))
        # One isotropic scale (half the longest side) so normalised distances stay Euclidean.
        self.scene_center = 0.5 * (bounds_min + bounds_max)
        self.scene_scale = float(0.5 * (bounds_max - bounds_min).max())
        self.render_chunk = config.render_chunk
        self.contracted, environment = unbounded_choices(config, scene.unbounded)
        region = camera_region(scene.train_cameras, self.scene_center) if self.contracted else None
        if region is not None:
            self.scene_center, self.scene_scale = region
        self.far = config.far_distance * self.scene_scale
        self.environment = _environment_map(scene, config.environment_width) if environment else None
        field = config.field
        self.pixel_batch = field.rays_per_step
        # The converters learn at the field's MLP rate, as the official NeRF recipe trains both at 5e-4.
        self.converter_lr = field.lr if isinstance(field, MlpFieldConfig) else field.mlp_lr
        if isinstance(field, MlpFieldConfig):
            self._build_mlp_fields(field)
        elif isinstance(field, GridFieldConfig):
            self._build_grid_field(field, scene)
        else:
            raise ValueError(
                f"NerfConfig.field must be a GridFieldConfig or MlpFieldConfig, got {type(field).__name__}"
            )

    def _build_mlp_fields(self, field: MlpFieldConfig) -> None:
        """The official recipe: a coarse and a fine MLP field."""
        if field.coarse_samples < 3 or field.fine_samples < 1:
            raise ValueError(
                "the paper field needs coarse_samples >= 3 and fine_samples >= 1, "
                f"got {field.coarse_samples} and {field.fine_samples}"
            )
        self.coarse_field = MlpRadianceField(field)
        self.fine_field = MlpRadianceField(field)

    def _build_grid_field(self, field: GridFieldConfig, scene: SceneInfo) -> None:
        """The CPU recipe: a hash-grid field, its occupancy grid, and the adaptive ray batch."""
        if field.max_samples_per_ray < 1 or not field.min_step > 0:
            raise ValueError(
                "the grid field needs max_samples_per_ray >= 1 and min_step > 0, got "
                f"{field.max_samples_per_ray} and {field.min_step}"
            )
        if not 1 <= field.rays_per_step <= field.max_rays_per_step or field.samples_per_step < 1:
            raise ValueError(
                "the grid field needs 1 <= rays_per_step <= max_rays_per_step and samples_per_step "
                f">= 1, got {field.rays_per_step}, {field.max_rays_per_step}, {field.samples_per_step}"
            )
        if self.contracted and field.occupancy_resolution % 4:
            raise ValueError(
                "with the contraction on, --backbone.field.occupancy-resolution must be a multiple of 4 "
                f"(its middle half is the unit region), got {field.occupancy_resolution}"
            )
        load_extension()  # built (or loaded) here, so a first build is never counted as training time
        self.grid_field = GridRadianceField(field)
        self.occupancy = OccupancyGrid(field.occupancy_resolution)
        self.occupancy.mark_seen(scene.train_cameras, self.field_to_world)
        # The adaptive ray batch is state: a resumed run continues with the same batch.
        self.register_buffer("rays_per_step", torch.tensor(field.rays_per_step))
        self.register_load_state_dict_post_hook(lambda module, keys: module._sync_pixel_batch())
        self._last_batch: tuple[int, int] | None = None

    @classmethod
    def presets(cls) -> dict[str, NerfConfig]:
        """cpu: grid field with occupancy-grid marching (the default); paper: the official MLP recipe."""
        return {"cpu": NerfConfig(field=GridFieldConfig()), "paper": NerfConfig(field=MlpFieldConfig())}

    @classmethod
    def tuning_space(cls, config: NerfConfig) -> dict[str, tuple]:
        """The grid field's two learning rates (features, tiny MLPs) around the cpu preset's, or
        the official MLP's one rate around its 5e-4."""
        if isinstance(config.field, GridFieldConfig):
            return {"field.grid_lr": (1e-2, 3e-2), "field.mlp_lr": (3e-3, 1e-2)}
        return {"field.lr": (5e-4, 1e-3)}

    @property
    def uses_grid(self) -> bool:
        return isinstance(self.config.field, GridFieldConfig)

    def parameter_groups(self) -> list[dict]:
        field = self.config.field
        if not self.uses_grid:
            return [
                {
                    "name": "nerf_mlp",
                    "params": list(self.coarse_field.parameters()) + list(self.fine_field.parameters()),
                    "lr": field.lr,
                }
            ]
        grid = self.grid_field
        # Instant-NGP's Adam: beta2 = 0.99, so rarely-hit grid cells follow their recent gradients.
        environment = (
            [{"name": "nerf_environment", "params": list(self.environment.parameters()), "lr": field.grid_lr}]
            if self.environment is not None
            else []
        )
        return environment + [
            {"name": "nerf_grid", "params": [grid.table], "lr": field.grid_lr, "betas": (0.9, 0.99)},
            {
                "name": "nerf_mlp",
                "params": list(grid.density_mlp.parameters()) + list(grid.color_mlp.parameters()),
                "lr": field.mlp_lr,
                "betas": (0.9, 0.99),
            },
        ]

    def learning_rate(self, group_name: str, step: int, base_lr: float) -> float:
        """paper: NeRF's lr * factor ** (step / decay_steps); cpu: decays to lr_final_factor at the
        run's last step, so a new run length (set_run_length) reshapes the rest of the schedule."""
        field = self.config.field
        if not self.uses_grid:
            return base_lr * field.lr_decay_factor ** (step / field.lr_decay_steps)
        return base_lr * field.lr_final_factor ** (min(step, self.max_steps) / max(self.max_steps, 1))

    def after_step(self, step: int, features: LdrFeatures, optimizer: torch.optim.Optimizer) -> None:
        """cpu: size the next ray batch to samples_per_step; refresh the occupancy grid every
        occupancy_update_every steps (from step 0)."""
        field = self.config.field
        if not self.uses_grid:
            return
        if self._last_batch is not None:
            rays, samples = self._last_batch
            wanted = field.samples_per_step * rays // max(samples, 1)
            self.rays_per_step.fill_(min(max(wanted, 1), field.max_rays_per_step))
            self._sync_pixel_batch()
            self._last_batch = None
        if step % field.occupancy_update_every == 0:
            self.refresh_occupancy(all_cells=step < field.occupancy_warmup_steps)

    def statistics(self) -> dict[str, float]:
        """cpu field: the share of camera-seen cells the occupancy grid keeps (what samples reach)."""
        if not self.uses_grid:
            return {}
        grid = self.occupancy
        return {"occupied_fraction": float(grid.occupied.sum()) / max(float(grid.seen.sum()), 1.0)}

    def _sync_pixel_batch(self) -> None:
        self.pixel_batch = int(self.rays_per_step)

    def refresh_occupancy(self, all_cells: bool = True) -> None:
        """Refresh the occupancy grid from the current field (see OccupancyGrid.update)."""
        field = self.config.field
        step_length = field.min_step
        # Opacity over one step >= threshold  <=>  density >= -ln(1 - threshold) / step.
        threshold = -math.log1p(-field.occupancy_threshold) / step_length
        self.occupancy.update(self.grid_field.density, field.occupancy_decay, threshold, all_cells=all_cells)

    @property
    def stochastic_sampling(self) -> bool:
        """Jitter samples only while training with gradients: evaluation, even in train mode
        under torch.no_grad, renders deterministically, so chunked and whole renders agree."""
        return self.training and torch.is_grad_enabled()

    def normalise(self, points: Tensor) -> Tensor:
        """World points [..., 3] -> the field's frame, where the box's longest side spans [-1, 1]."""
        return (points - self.scene_center.to(points)) / self.scene_scale

    def to_world(self, points: Tensor) -> Tensor:
        """Normalised points [..., 3] -> world points (the inverse of normalise)."""
        return points * self.scene_scale + self.scene_center.to(points)

    def field_points(self, points: Tensor) -> Tensor:
        """World points [..., 3] -> where the grid field and the occupancy grid read them, [-1, 1]^3:
        normalised, and with the contraction on, contracted and halved (the unit region is the
        middle half)."""
        normalised = self.normalise(points)
        return contract(normalised) / 2.0 if self.contracted else normalised

    def field_to_world(self, points: Tensor) -> Tensor:
        """Field points [..., 3] -> world points (the inverse of field_points; with the contraction
        on, the cube's surface stands for points 1000 half sides away)."""
        return self.to_world(uncontract(2.0 * points) if self.contracted else points)

    def render_ldr_features(self, camera: Camera) -> LdrFeatures:
        """Per-sample LDR colours of the camera's rays and their compositing closure.

        paper field: colors, raw_colors [N_rays, S, 3] (N_rays = prod(output_shape)) and composite
        [N_rays, S, C] -> [*camera.output_shape, C], auxiliary = [the coarse network's LdrFeatures].
        cpu field: the samples are packed, colors [M, 3] and composite [M, C] -> [*output_shape, C],
        holding only the M samples that contribute (extras "ray_indices" [M] says whose they are).
        Both: extras "weights" and "sample_distances" (t along the unit ray) [N_rays, S], "depth"
        (expected distance, 0 where empty) and "alpha" (accumulation) [*output_shape].
        """
        origins, directions = camera.rays()
        device = self.bounds_min.device
        origins, directions = origins.reshape(-1, 3).to(device), directions.reshape(-1, 3).to(device)
        output_shape = camera.output_shape
        render = self._render_grid if self.uses_grid else self._render_paper
        return render(origins, directions, camera, output_shape, self.stochastic_sampling)

    def _features(
        self, density: Tensor, raw_color: Tensor, t: Tensor, t_far: Tensor, output_shape: tuple[int, ...]
    ) -> LdrFeatures:
        weights = compositing_weights(density, sample_deltas(t, t_far) / self.scene_scale)
        extras = {
            "weights": weights,
            "sample_distances": t,
            "depth": (weights * t).sum(dim=-1).reshape(output_shape),
            "alpha": weights.sum(dim=-1).reshape(output_shape),
        }
        return LdrFeatures(
            colors=torch.sigmoid(raw_color),
            raw_colors=raw_color,
            composite=make_composite(weights, output_shape, self.background),
            extras=extras,
        )

    def _query(self, field, origins: Tensor, directions: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """Field at every sample: density [N, S], raw colour [N, S, 3]."""
        positions = self.normalise(origins[:, None] + t[..., None] * directions[:, None])
        rays, samples = t.shape
        density, raw_color = field(
            positions.reshape(-1, 3), directions[:, None].expand(rays, samples, 3).reshape(-1, 3)
        )
        return density.reshape(rays, samples), raw_color.reshape(rays, samples, 3)

    def _render_paper(
        self, origins: Tensor, directions: Tensor, camera: Camera, output_shape: tuple[int, ...], stochastic: bool
    ) -> LdrFeatures:
        paper = self.config.field
        bounds = (self.bounds_min, self.bounds_max) if paper.clip_to_bounds else None
        t_near, t_far = ray_segments(origins, directions, camera.near, camera.far, bounds)
        t_coarse = sample_stratified(t_near, t_far, paper.coarse_samples, perturb=stochastic)
        coarse = self._features(
            *self._query(self.coarse_field, origins, directions, t_coarse), t_coarse, t_far, output_shape
        )
        # NeRF's importance sampling: bins between coarse samples, interior weights, no gradient.
        with torch.no_grad():
            mids = 0.5 * (t_coarse[:, 1:] + t_coarse[:, :-1])
            t_importance = sample_pdf(
                mids, coarse.extras["weights"][:, 1:-1].detach(), paper.fine_samples, deterministic=not stochastic
            )
            t_fine = torch.sort(torch.cat([t_coarse, t_importance], dim=-1), dim=-1).values
        fine = self._features(*self._query(self.fine_field, origins, directions, t_fine), t_fine, t_far, output_shape)
        fine.auxiliary = [coarse]
        return fine

    def _segments(self, origins: Tensor, directions: Tensor, camera: Camera) -> tuple[Tensor, Tensor]:
        """Each ray's [t_near, t_far] inside the scene box, or with the contraction on, inside the
        unit region (the box's cube), whose far part then reaches far_distance."""
        if not self.contracted:
            return ray_segments(origins, directions, camera.near, camera.far, (self.bounds_min, self.bounds_max))
        center, half = self.scene_center.to(origins), self.scene_scale
        return ray_segments(origins, directions, camera.near, max(camera.far, self.far), (center - half, center + half))

    def _far_start(self, t_far: Tensor) -> Tensor:
        """Where a ray's samples linear in disparity begin: its exit of the unit region (> 0)."""
        return t_far.clamp_min(1e-6 * self.scene_scale)

    def march(
        self, origins: Tensor, directions: Tensor, camera: Camera, stochastic: bool
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Marched samples of the cpu field, S = max_samples_per_ray per ray at most (with the
        contraction on, followed by far_samples candidates beyond the unit region, kept where occupied).

        Returns t, delta [N, S] (world units; delta 0 past a ray's samples, where t stays at the
        ray's far end, so rows are sorted), the flat indices [M] of the real samples in [N * S],
        and fraction [N, S]: where in its bin of occupied length each sample sits (0.5 unless jittered).
        With the contraction on, t and delta beyond the unit region are warped distances
        (unbounded.unwarp; t itself inside it).
        """
        field = self.config.field
        t_near, t_far = self._segments(origins, directions, camera)
        samples = field.max_samples_per_ray
        fraction = (
            torch.rand(origins.shape[0], samples, device=origins.device)
            if stochastic
            else torch.full((origins.shape[0], samples), 0.5, device=origins.device)
        )
        occupied = self.occupancy.occupied
        if self.contracted:  # the unit region is the middle half of the grid
            quarter = occupied.shape[0] // 4
            occupied = occupied[quarter:-quarter, quarter:-quarter, quarter:-quarter]
        t, delta, counts = march_rays(
            origins,
            directions,
            t_near,
            t_far,
            occupied,
            self.scene_center,
            self.scene_scale,
            field.min_step * self.scene_scale,
            samples,
            fraction if stochastic else None,
        )
        real = torch.arange(samples, device=counts.device) < counts[:, None]
        t = torch.where(real, t, t_far[:, None].expand_as(t))
        if self.contracted:
            t_start = self._far_start(t_far)
            jitter = torch.rand(origins.shape[0], field.far_samples, device=origins.device) if stochastic else None
            u, du, far_fraction = far_candidates(t_start, self.scene_scale, field.far_samples, jitter)
            far_points = (
                origins[:, None] + unwarp(u, t_start, self.scene_scale, self.far)[..., None] * directions[:, None]
            )
            far_real = self.occupancy.occupied_at(self.field_points(far_points))
            t, fraction, real = (
                torch.cat([t, u], -1),
                torch.cat([fraction, far_fraction], -1),
                torch.cat([real, far_real], -1),
            )
            delta = torch.cat([delta, torch.where(far_real, du, torch.zeros_like(du))], -1)
        return t, delta, real.reshape(-1).nonzero()[:, 0], fraction

    def _distances(
        self, origins: Tensor, directions: Tensor, t: Tensor, delta: Tensor, t_far: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Marched t, delta [N, S] (see march) -> distances t [N, S] and the lengths the samples stand
        for in the field's frame (normalised; with the contraction on, contracted), which densities are per."""
        if not self.contracted:
            return t, delta / self.scene_scale
        t_start = self._far_start(t_far)
        t0 = unwarp(t, t_start, self.scene_scale, self.far)
        t1 = unwarp(t + delta, t_start, self.scene_scale, self.far)
        lengths = contracted_lengths(self.normalise(origins), directions / self.scene_scale, t0, t1)
        return t0, torch.where(delta > 0, lengths, torch.zeros_like(lengths))

    def place_samples(
        self, origins: Tensor, directions: Tensor, camera: Camera, stochastic: bool
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Where the cpu field is shaded: marched samples in occupied cells, then a density pass
        without gradients places importance_samples per ray from their weights (or, with 0, keeps
        the marched samples in front of early_stop_transmittance while training).

        Returns t [N, S] (world units, rows sorted), the lengths the samples stand for in the field's
        frame [N, S] (see _distances) and the flat indices [M] of the samples to shade in [N * S].
        """
        field = self.config.field
        marched, delta, flat, fraction = self.march(origins, directions, camera, stochastic)
        t_far = self._segments(origins, directions, camera)[1]
        t, lengths = self._distances(origins, directions, marched, delta, t_far)
        wants_proposal = field.importance_samples > 0 or (
            torch.is_grad_enabled() and field.early_stop_transmittance > 0
        )
        if not wants_proposal or not flat.numel():
            return t, lengths, flat
        ray_of = flat // t.shape[1]
        with torch.no_grad():
            positions = self.field_points(origins[ray_of] + t.reshape(-1)[flat, None] * directions[ray_of])
            density = (
                self.occupancy.lookup(positions)
                if field.proposal == "cache" and field.importance_samples > 0
                else self.grid_field.density(positions)
            )
            weights = self._weights(density, flat, lengths)
            if field.importance_samples > 0:
                marched, delta = resample_occupied(
                    marched, delta, fraction, weights, field.importance_samples, deterministic=not stochastic
                )
                t, lengths = self._distances(origins, directions, marched, delta, t_far)
                return t, lengths, (delta > 0).reshape(-1).nonzero()[:, 0]
            transmittance = 1.0 - (torch.cumsum(weights, dim=-1) - weights)
            return t, lengths, flat[transmittance.reshape(-1)[flat] > field.early_stop_transmittance]

    def _render_grid(
        self, origins: Tensor, directions: Tensor, camera: Camera, output_shape: tuple[int, ...], stochastic: bool
    ) -> LdrFeatures:
        """Packed features: the field runs on the placed samples (place_samples) and only those
        whose weight reaches min_sample_weight get a colour; with the environment background,
        each ray ends with one more sample, the map's colour in its direction, weighted by the
        transmittance left."""
        field = self.config.field
        t, lengths, flat = self.place_samples(origins, directions, camera, stochastic)
        rays, samples = t.shape
        if stochastic:
            self._last_batch = (rays, flat.numel())
        ray_of = flat // samples
        positions = self.field_points(origins[ray_of] + t.reshape(-1)[flat, None] * directions[ray_of])
        density, geometry = self.grid_field.density_and_geometry(positions)
        weights = self._weights(density, flat, lengths)
        sample_weights = weights.reshape(-1)[flat]
        coloured = sample_weights.detach() >= max(field.min_sample_weight, torch.finfo(weights.dtype).tiny)
        ray_indices, kept_weights = ray_of[coloured], sample_weights[coloured]
        raw_color = self.grid_field.color(geometry[coloured], directions[ray_indices])
        accumulation = weights.sum(dim=-1)
        covered = accumulation
        if self.environment is not None:
            left = (1.0 - accumulation).clamp_min(0.0)
            raw_color = torch.cat([raw_color, self.environment(directions)])
            ray_indices = torch.cat([ray_indices, torch.arange(rays, device=ray_indices.device)])
            kept_weights, covered = torch.cat([kept_weights, left]), accumulation + left
        extras = {
            "weights": weights,
            "sample_distances": t,
            "ray_indices": ray_indices,
            "depth": (weights * t).sum(dim=-1).reshape(output_shape),
            "alpha": accumulation.reshape(output_shape),
        }
        composite = make_packed_composite(kept_weights, ray_indices, covered, output_shape, self.background)
        colors = F.softplus(raw_color) if field.color_activation == "softplus" else torch.sigmoid(raw_color)
        bound = field.l2h_input_bound if self.contracted else 0.0  # interiors' lights live beyond it
        return LdrFeatures(
            colors=colors,
            raw_colors=raw_color,
            composite=composite,
            extras=extras,
            l2h_inputs=bounded_logit(raw_color, bound) if field.l2h_input == "raw" else None,
        )

    @staticmethod
    def _weights(density: Tensor, flat: Tensor, deltas: Tensor) -> Tensor:
        """Compositing weights [N, S] of packed densities [K] at flat indices [K] of [N, S]."""
        dense = deltas.new_zeros(deltas.numel()).index_put((flat,), density).reshape(deltas.shape)
        return compositing_weights(dense, deltas)
