"""The 3D Gaussian Splatting backbone: parameters, rendering, schedules, density control."""

import math
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import torch
from torch import Tensor, nn

from backbones.gs.ply import export_ply
from backbones.gs.rasterizer import project_gaussians, rasterize
from backbones.gs.sh import eval_sh, num_sh_bases, rgb_to_sh, view_directions
from backbones.gs.strategy import DensityControl, DensityControlSchedule, DensityControlState
from mono_hdr_plugin.backbone import Backbone, LdrFeatures, SceneInfo
from mono_hdr_plugin.cameras import Camera
from mono_hdr_plugin.validation import NON_NEGATIVE, POSITIVE, at_least, between


@dataclass
class GaussianConfig:
    """Hyper-parameters of the 3DGS backbone (defaults: the official 3DGS recipe)."""

    sh_degree: int = 3
    """Highest spherical-harmonics degree of the view-dependent colour (0 to 3)."""
    sh_increase_every: int = 1000
    """Raise the active SH degree by one every this many steps of a 30k run (scaled to the run)."""
    random_init_points: int = 10_000
    """Gaussians placed uniformly in the scene bounds when the scene gives no points."""
    init_opacity: float = 0.1
    """Opacity of every Gaussian at initialisation."""
    lr_means: float = 1.6e-4
    """Initial position learning rate, times the scene extent."""
    lr_means_final: float = 1.6e-6
    """Position learning rate at the last step (exponential decay), times the scene extent."""
    lr_sh_dc: float = 2.5e-3
    """Learning rate of the SH degree-0 (base colour) coefficients."""
    lr_sh_rest: float = 2.5e-3 / 20
    """Learning rate of the higher SH coefficients."""
    lr_opacities: float = 0.05
    """Learning rate of the opacity logits."""
    lr_scales: float = 5e-3
    """Learning rate of the log scales."""
    lr_quats: float = 1e-3
    """Learning rate of the rotation quaternions."""
    refine_start: int = 500
    """First densification step of a 30k run (scaled to the run length)."""
    refine_stop: int = 15_000
    """Last densification step of a 30k run (scaled to the run length)."""
    refine_every: int = 100
    """Densify every this many steps of a 30k run (scaled to the run length)."""
    min_refine_every: int = 10
    """Lower bound on the scaled densification interval, so short runs still average gradients."""
    reset_opacity_every: int = 3000
    """Reset opacities every this many steps of a 30k run (scaled to the run length)."""
    grad_threshold: float = 2e-4
    """Densify Gaussians whose mean view-space gradient (NDC units) exceeds this."""
    percent_dense: float = 0.01
    """Gaussians larger than this fraction of the scene extent are split, smaller ones cloned."""
    prune_opacity: float = 0.005
    """Prune Gaussians less opaque than this."""
    max_screen_size: float = 20.0
    """After the first opacity reset, prune Gaussians wider than this many pixels."""
    max_gaussians: int = 300_000
    """Stop growing beyond this many Gaussians (a CPU memory and time budget)."""
    backend: str = "kernel"
    """Rasteriser: "kernel" (C++ CPU extension) or "torch" (the slow reference twin)."""

    flag_rules: ClassVar = {
        "sh_degree": between(0, 3), "sh_increase_every": at_least(1), "random_init_points": at_least(1),
        "init_opacity": between(0, 1, low_open=True, high_open=True), "lr_means": POSITIVE, "lr_means_final": POSITIVE,
        "lr_sh_dc": POSITIVE, "lr_sh_rest": POSITIVE, "lr_opacities": POSITIVE, "lr_scales": POSITIVE,
        "lr_quats": POSITIVE, "refine_start": NON_NEGATIVE, "refine_stop": NON_NEGATIVE, "refine_every": at_least(1),
        "min_refine_every": at_least(1), "reset_opacity_every": at_least(1), "grad_threshold": NON_NEGATIVE,
        "percent_dense": POSITIVE, "prune_opacity": between(0, 1, high_open=True), "max_screen_size": POSITIVE,
        "max_gaussians": at_least(1)}


class _RenderExtras(dict):
    """extras of one render: alpha and depth appear when the image is composited; read
    before that, they are rendered on their own (an extra pass)."""

    def __init__(self, render_geometry, **items):
        super().__init__(**items)
        self._render_geometry = render_geometry

    def __missing__(self, key):
        if key in ("alpha", "depth"):
            self._render_geometry()
            return dict.__getitem__(self, key)
        raise KeyError(key)

    def __contains__(self, key):
        return key in ("alpha", "depth") or dict.__contains__(self, key)

    def get(self, key, default=None):
        return self[key] if key in self else default


class GaussianBackbone(Backbone):
    """3D Gaussians with SH colours, rendered by the tiled CPU rasteriser."""

    config_class = GaussianConfig
    loss_kind = "l1_dssim"
    paper_backbone = "3DGS"
    pixel_batch = None

    def __init__(self, config: GaussianConfig, scene: SceneInfo):
        super().__init__(config, scene)
        if config.backend not in ("kernel", "torch"):
            raise ValueError(f"backend must be 'kernel' or 'torch', got {config.backend!r}")
        num_sh_bases(config.sh_degree)  # validates the degree
        self.scene_extent = scene.extent if scene.train_cameras else float(
            (scene.bounds_max - scene.bounds_min).norm() / 2)
        means, colors = self._initial_points(config, scene)
        n = means.shape[0]
        sh_dc = rgb_to_sh(colors)[:, None, :]
        self.means = nn.Parameter(means)
        self.sh_dc = nn.Parameter(sh_dc)
        self.sh_rest = nn.Parameter(torch.zeros(n, num_sh_bases(config.sh_degree) - 1, 3))
        self.log_scales = nn.Parameter(torch.log(_nearest_neighbour_distance(means))[:, None].repeat(1, 3))
        self.quats = nn.Parameter(torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1))
        self.opacity_logits = nn.Parameter(torch.full((n,), math.log(config.init_opacity / (1 - config.init_opacity))))
        self.active_sh_degree = 0
        self.density_control = self._density_control()

    @staticmethod
    def _initial_points(config: GaussianConfig, scene: SceneInfo) -> tuple[Tensor, Tensor]:
        if scene.points is not None and len(scene.points) > 0:
            points = scene.points.detach().float().reshape(-1, 3).clone()  # training moves the means in place
            if scene.point_colors is None:
                return points, torch.full_like(points, 0.5)
            colors = scene.point_colors.detach().reshape(-1, 3)
            colors = colors.float() / 255.0 if not colors.is_floating_point() else colors.float()
            if colors.shape[0] != points.shape[0]:
                raise ValueError(f"scene.point_colors has {colors.shape[0]} rows for {points.shape[0]} points: "
                                 "give one colour per point or none")
            return points, colors.clamp(0, 1)
        low, high = scene.bounds_min.float(), scene.bounds_max.float()
        if not (high > low).all():
            raise ValueError(f"scene bounds must satisfy min < max, got {low.tolist()} and {high.tolist()}")
        means = low + torch.rand(config.random_init_points, 3) * (high - low)
        return means, torch.rand(config.random_init_points, 3)

    def _density_control(self) -> DensityControl:
        c = self.config
        schedule = DensityControlSchedule.scaled(self.max_steps, c.refine_start, c.refine_stop, c.refine_every,
                                                 c.reset_opacity_every, c.min_refine_every)
        return DensityControl(schedule, self.scene_extent, grad_threshold=c.grad_threshold,
                              percent_dense=c.percent_dense, prune_opacity=c.prune_opacity,
                              max_screen_size=c.max_screen_size, max_gaussians=c.max_gaussians)

    @classmethod
    def benchmarks(cls) -> dict:
        """`mono-hdr bench raster`: the C++ kernel against its torch twin, 3 vs 6 channels."""
        from backbones.gs.benchmark import BenchRasterConfig, bench_raster_command  # noqa: PLC0415

        return {"raster": (BenchRasterConfig, bench_raster_command)}

    @classmethod
    def presets(cls) -> dict[str, GaussianConfig]:
        """paper: the official 3DGS recipe (30k steps, scaled to the run length)."""
        return {"paper": GaussianConfig()}

    def set_run_length(self, max_steps: int) -> None:
        super().set_run_length(max_steps)
        statistics = self.density_control.state if hasattr(self, "density_control") else None
        self.density_control = self._density_control()
        if statistics is not None:  # a time-budget re-estimate must not forget the gathered gradients
            self.density_control.state = statistics

    @property
    def num_gaussians(self) -> int:
        return self.means.shape[0]

    def statistics(self) -> dict[str, float]:
        return {"gaussians": self.num_gaussians}

    def parameter_groups(self) -> list[dict]:
        c = self.config
        return [
            {"name": "means", "params": [self.means], "lr": c.lr_means * self.scene_extent},
            {"name": "sh_dc", "params": [self.sh_dc], "lr": c.lr_sh_dc},
            {"name": "sh_rest", "params": [self.sh_rest], "lr": c.lr_sh_rest},
            {"name": "log_scales", "params": [self.log_scales], "lr": c.lr_scales},
            {"name": "quats", "params": [self.quats], "lr": c.lr_quats},
            {"name": "opacity_logits", "params": [self.opacity_logits], "lr": c.lr_opacities},
        ]

    def learning_rate(self, group_name: str, step: int, base_lr: float) -> float:
        """3DGS position schedule: log-linear from lr_means to lr_means_final over the run."""
        if group_name != "means":
            return base_lr
        progress = min(max(step / max(self.max_steps, 1), 0.0), 1.0)
        final = base_lr * self.config.lr_means_final / self.config.lr_means
        return math.exp((1 - progress) * math.log(base_lr) + progress * math.log(final))

    def activated(self) -> dict[str, Tensor]:
        """Render-ready parameters: means [N,3], quats [N,4], scales [N,3], opacities [N], sh [N,K,3]."""
        # clamping the log-scale keeps exp finite, so culled Gaussians never see inf * 0 gradients
        return {"means": self.means, "quats": self.quats, "scales": torch.exp(self.log_scales.clamp(-20, 20)),
                "opacities": torch.sigmoid(self.opacity_logits), "sh": torch.cat([self.sh_dc, self.sh_rest], 1)}

    def render_ldr_features(self, camera: Camera) -> LdrFeatures:
        g = self.activated()
        raw_colors = eval_sh(self.active_sh_degree, g["sh"], view_directions(g["means"], camera.center))
        colors = (raw_colors + 0.5).clamp_min(0)
        projected = project_gaussians(g["means"], g["quats"], g["scales"], g["opacities"], camera,
                                      backend=self.config.backend)
        if projected.means2d.requires_grad:
            projected.means2d.retain_grad()

        def render_geometry():
            composite(projected.means2d.new_zeros(self.num_gaussians, 0))

        extras = _RenderExtras(render_geometry, means2d=projected.means2d, radii=projected.radii,
                               visibility=projected.radii > 0, projected=projected,
                               image_size=(camera.width, camera.height))

        def composite(values: Tensor) -> Tensor:
            """values [N, C] -> image [H, W, C]; also leaves alpha and depth [H, W, 1] in extras."""
            image, alpha = rasterize(projected, torch.cat([values, projected.depths[:, None]], 1))
            extras["alpha"] = alpha
            # expected depth of the visible surface, 0 where nothing was hit
            extras["depth"] = image[..., -1:] / alpha.clamp_min(1e-6)
            return image[..., :-1]

        return LdrFeatures(colors=colors, raw_colors=raw_colors, composite=composite, extras=extras)

    @torch.no_grad()
    def after_step(self, step: int, features: LdrFeatures, optimizer: torch.optim.Optimizer) -> None:
        """Raise the SH degree on schedule and run density control (keeps Adam state aligned)."""
        interval = max(1, round(self.config.sh_increase_every * self.max_steps / 30_000))
        self.active_sh_degree = min(self.config.sh_degree, (step + 1) // interval)
        width, height = features.extras["image_size"]
        self.density_control.step_post_backward(self, optimizer, step, features.extras["means2d"],
                                                features.extras["radii"], width, height)

    def load_gaussians(self, tensors: dict[str, Tensor]) -> None:
        """Replace all Gaussians (e.g. from load_ply); rebuild the optimiser afterwards."""
        for name in ("means", "sh_dc", "sh_rest", "log_scales", "quats", "opacity_logits"):
            if name not in tensors:
                raise ValueError(f"missing {name!r}: pass the dict load_ply returns")
            setattr(self, name, nn.Parameter(tensors[name].float().clone()))

    def export_ply(self, path) -> Path:
        """Write the Gaussians as a standard 3DGS PLY (`mono-hdr export` looks for this method)."""
        return export_ply(self, path)

    def get_extra_state(self) -> dict:
        """State outside the parameters that shapes renders and training: the active SH degree
        (a model loaded without it renders with degree 0) and the density statistics."""
        state = self.density_control.state
        return {"active_sh_degree": self.active_sh_degree, "grad2d_sum": state.grad2d_sum,
                "visible_count": state.visible_count, "max_radii": state.max_radii}

    def set_extra_state(self, state: dict) -> None:
        self.active_sh_degree = int(state["active_sh_degree"])
        self.density_control.state = DensityControlState(
            state["grad2d_sum"].clone(), state["visible_count"].clone(), state["max_radii"].clone())

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # densification changes N: take the checkpoint's shapes before loading values
        for name in ("means", "sh_dc", "sh_rest", "log_scales", "quats", "opacity_logits"):
            if prefix + name in state_dict:
                setattr(self, name, nn.Parameter(torch.empty_like(state_dict[prefix + name])))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


def _nearest_neighbour_distance(points: Tensor, k: int = 3, chunk: int = 1024) -> Tensor:
    """Root mean squared distance [N] to the k nearest other points (3DGS initial scale)."""
    n = points.shape[0]
    if n <= 1:
        return torch.full((n,), 0.01)
    k = min(k, n - 1)
    result = []
    for start in range(0, n, chunk):
        d2 = torch.cdist(points[start:start + chunk], points).square()
        nearest = torch.topk(d2, k + 1, largest=False).values[:, 1:]  # drop the point itself
        result.append(nearest.mean(-1))
    return torch.cat(result).clamp_min(1e-7).sqrt()
