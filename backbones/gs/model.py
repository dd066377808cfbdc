"""The 3D Gaussian Splatting backbone: parameters, rendering, schedules, densification."""

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import torch
import tyro
from torch import Tensor, nn

from backbones.gs._extension import load_extension
from backbones.gs.ply import export_ply
from backbones.gs.rasterizer import check_backend, project_gaussians, rasterize
from backbones.gs.rigid import camera_as_world_motion, move_gaussians
from backbones.gs.sh import num_sh_bases, rgb_to_sh, visible_colors
from backbones.gs.sky import (
    background_rows,
    export_environment,
    make_environment,
    random_points_in_view,
    uses_environment,
)
from backbones.gs.sky_gaussians import SkyGaussians, export_sky, scene_projection, scene_rows, with_sky
from backbones.gs.strategy import GAUSSIAN_PARAMETERS, REFERENCE_STEPS, DefaultStrategy, McmcStrategy
from mono_hdr_plugin.core.backbone import Backbone, LdrFeatures, SceneInfo
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.core.validation import POSITIVE, at_least, between, one_of


@dataclass
class GaussianConfig:
    """Hyper-parameters of the 3DGS backbone. Field defaults are the official 3DGS recipe
    (`--preset paper`); `--preset cpu`, the default, changes some for a minutes-long CPU run."""

    sh_degree: int = 3
    """Highest spherical-harmonics degree of the view-dependent colour (0 to 3)."""
    sh_increase_every: int = 1000
    """Raise the active SH degree by one every this many steps of a 30k run (scaled to the run)."""
    random_init_points: int = 10_000
    """Gaussians placed uniformly in the scene bounds when the scene gives no points."""
    init_opacity: float = 0.1
    """Opacity of every Gaussian at initialisation."""
    init_scale: float = 1.0
    """Initial scale: this times the mean distance to the 3 nearest initial points."""
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
    strategy: tyro.conf.AvoidSubcommands[McmcStrategy | DefaultStrategy] = field(default_factory=DefaultStrategy)
    """Densification: the preset chooses it (cpu: 3DGS-MCMC with a Gaussian budget, paper: the
    official clone/split/prune); its settings are the --backbone.strategy.* flags."""
    backend: str = "kernel"
    """Rasteriser: "kernel" (C++ CPU extension) or "torch" (the slow reference twin)."""
    background: Literal["auto", "environment", "sky-gaussians", "none"] = "auto"
    """What lies behind the splats: "environment" (a learned map of the sky at infinity, composited
    with the weight the splats leave), "sky-gaussians" (a fixed shell of Gaussians far around the
    scene, rasterised with the splats; only their colours learn), "none", or "auto" (environment
    iff the scene is unbounded)."""
    lr_environment: float = 0.01
    """Learning rate of the environment map's raw colours."""
    sky_gaussians: int = 4096
    """With sky-gaussians: about this many, spread evenly over the directions the training cameras see."""
    sky_scale: float = 0.8
    """With sky-gaussians: their standard deviation, in units of the shell's point spacing (the
    square root of the area per point); 0.8 leaves less than 1 % of any pixel uncovered."""
    lr_sky: float = 0.01
    """Learning rate of the sky Gaussians' raw colours."""

    flag_rules: ClassVar = {
        "sh_degree": between(0, 3),
        "sh_increase_every": at_least(1),
        "random_init_points": at_least(1),
        "init_opacity": between(0, 1, low_open=True, high_open=True),
        "init_scale": POSITIVE,
        "lr_means": POSITIVE,
        "lr_means_final": POSITIVE,
        "lr_sh_dc": POSITIVE,
        "lr_sh_rest": POSITIVE,
        "lr_opacities": POSITIVE,
        "lr_scales": POSITIVE,
        "lr_quats": POSITIVE,
        "background": one_of("auto", "environment", "sky-gaussians", "none"),
        "lr_environment": POSITIVE,
        "sky_gaussians": at_least(1),
        "sky_scale": POSITIVE,
        "lr_sky": POSITIVE,
    }
    """The strategy's flags follow its own table (McmcStrategy, DefaultStrategy)."""


def cpu_preset() -> GaussianConfig:
    """Minutes on a CPU: 3DGS-MCMC within a Gaussian budget, a faster SH ramp and colour rates
    that let log-radiance colours (HDR-GS) move as far as LDR ones in a short run.

    Chosen by the sweep in benchmarks/gs_cpu_sweep.py on the built-in scenes (results in
    benchmarks/results/gs_cpu_sweep/); the same values serve every method.
    """
    return GaussianConfig(
        init_opacity=0.5, init_scale=0.5, lr_sh_dc=0.01, lr_sh_rest=0.01 / 20, strategy=McmcStrategy()
    )


class GaussianBackbone(Backbone):
    """3D Gaussians with SH colours, rendered by the tiled CPU rasteriser."""

    config_class = GaussianConfig
    loss_kind = "l1_dssim"
    paper_backbone = "3DGS"
    pixel_batch = None

    def __init__(self, config: GaussianConfig, scene: SceneInfo):
        super().__init__(config, scene)
        check_backend(config.backend)
        if config.backend == "kernel":
            load_extension()  # built (or loaded) here, so a first build is never counted as training time
        num_sh_bases(config.sh_degree)  # validates the degree
        self.scene_extent = scene.extent
        training_pixels = sum(camera.width * camera.height for camera in scene.train_cameras)
        means, colors = self._initial_points(config, scene)
        self.full_budget = config.strategy.budget(training_pixels) if training_pixels else means.shape[0]
        self.budget = self.full_budget
        """The most Gaussians density control grows to now: the full budget scaled to the pixels of the
        current coarse-to-fine level (set_image_scale)."""
        if means.shape[0] > self.budget:  # start within the budget: a random subset
            keep = torch.randperm(means.shape[0])[: self.budget]
            means, colors = means[keep], colors[keep]
        n = means.shape[0]
        self.means = nn.Parameter(means)
        self.sh_dc = nn.Parameter(rgb_to_sh(colors)[:, None, :])
        self.sh_rest = nn.Parameter(torch.zeros(n, num_sh_bases(config.sh_degree) - 1, 3))
        scale = config.init_scale * _nearest_neighbour_distance(means)
        self.log_scales = nn.Parameter(torch.log(scale)[:, None].repeat(1, 3))
        self.quats = nn.Parameter(torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1))
        self.opacity_logits = nn.Parameter(torch.full((n,), math.log(config.init_opacity / (1 - config.init_opacity))))
        self.active_sh_degree = 0
        self.strategy_state = config.strategy.initial_state(n)
        # an nn.Module child when used: its textures reach state_dict and stay out of density control
        self.environment = make_environment(scene) if uses_environment(config.background, scene) else None
        # likewise a child module, outside GAUSSIAN_PARAMETERS: density control never sees it
        sky = config.background == "sky-gaussians"
        self.sky = SkyGaussians(scene, config.sky_gaussians, config.sky_scale) if sky else None

    @staticmethod
    def _initial_points(config: GaussianConfig, scene: SceneInfo) -> tuple[Tensor, Tensor]:
        """The scene's points (COLMAP, studio surface samples) with their colours, else random
        points in the scene bounds."""
        if scene.points is not None and len(scene.points) > 0:
            points = scene.points.detach().float().reshape(-1, 3).clone()  # training moves the means in place
            if scene.point_colors is None:
                return points, torch.full_like(points, 0.5)
            colors = scene.point_colors.detach().reshape(-1, 3)
            colors = colors.float() / 255.0 if not colors.is_floating_point() else colors.float()
            if colors.shape[0] != points.shape[0]:
                raise ValueError(
                    f"scene.point_colors has {colors.shape[0]} rows for {points.shape[0]} points: "
                    "give one colour per point or none"
                )
            return points, colors.clamp(0, 1)
        low, high = scene.bounds_min.float(), scene.bounds_max.float()
        if not (high > low).all():
            raise ValueError(f"scene bounds must satisfy min < max, got {low.tolist()} and {high.tolist()}")
        if scene.unbounded and scene.train_cameras:
            means = random_points_in_view(config.random_init_points, low, high, scene.train_cameras)
        else:
            means = low + torch.rand(config.random_init_points, 3) * (high - low)
        return means, torch.rand(config.random_init_points, 3)

    @classmethod
    def tuning_space(cls, config: GaussianConfig) -> dict[str, tuple]:
        """The recipe table's grid, around the cpu preset's base-colour and position rates."""
        return {"lr_sh_dc": (0.005, 0.01), "lr_means": (1.6e-4, 4.8e-4)}

    @classmethod
    def presets(cls) -> dict[str, GaussianConfig]:
        """cpu (default): budgeted 3DGS-MCMC for 2-10 minute runs; paper: the official 3DGS recipe
        (30k steps, clone/split/prune), both scaled to the run length."""
        return {"cpu": cpu_preset(), "paper": GaussianConfig()}

    @property
    def num_gaussians(self) -> int:
        return self.means.shape[0]

    def statistics(self) -> dict[str, float]:
        return {"gaussians": self.num_gaussians}

    def parameter_groups(self) -> list[dict]:
        c = self.config
        rates = {
            "means": c.lr_means * self.scene_extent,
            "sh_dc": c.lr_sh_dc,
            "sh_rest": c.lr_sh_rest,
            "log_scales": c.lr_scales,
            "quats": c.lr_quats,
            "opacity_logits": c.lr_opacities,
        }
        groups = [
            {"name": name, "params": [getattr(self, name)], "lr": rates[name], "per_row": True}
            for name in GAUSSIAN_PARAMETERS
        ]
        if self.environment is not None:
            groups.append(
                {"name": "environment", "params": list(self.environment.parameters()), "lr": c.lr_environment}
            )
        if self.sky is not None:
            groups.append({"name": "sky", "params": [self.sky.colors], "lr": c.lr_sky})
        return groups

    def visible_rows(self, features: LdrFeatures) -> Tensor:
        """The scene Gaussians the render projected into its image (a crop's: those whose box meets it)."""
        projected = features.extras["projected"]
        return projected.index if self.sky is None else projected.index[: scene_rows(projected, self.num_gaussians)]

    def learning_rate(self, group_name: str, step: int, base_lr: float) -> float:
        """3DGS position schedule: log-linear from lr_means to lr_means_final over the run."""
        if group_name != "means":
            return base_lr
        progress = min(max(step / max(self.max_steps, 1), 0.0), 1.0)
        final = base_lr * self.config.lr_means_final / self.config.lr_means
        return math.exp((1 - progress) * math.log(base_lr) + progress * math.log(final))

    def regularisation(self) -> dict[str, Tensor]:
        """The strategy's loss terms on the Gaussians (3DGS-MCMC: opacity and scale)."""
        return self.config.strategy.regularisation(self)

    def render_ldr_features(self, camera: Camera) -> LdrFeatures:
        """Colours of the V Gaussians visible in `camera` ([V, 3]), then with an environment one
        background row per pixel ([V + H * W, 3], row-major); `composite` takes [rows, C] and adds
        the background rows with weight 1 - alpha. With sky Gaussians the V rows are the visible
        scene Gaussians followed by the visible sky Gaussians, rasterised together.

        extras: "projected" (the ProjectedGaussians: visible index, screen means whose gradient
        densification reads, radii; with sky Gaussians their indices follow the scene's N, and
        after_step hands density control the scene's rows only), "alpha" [H, W, 1] once
        `composite` has run (the coverage of everything rasterised, the sky included), and
        "render_depth", a function that rasterises the expected depth of the scene's Gaussians
        [H, W, 1] (an extra pass, only when called; 0 where no scene Gaussian was hit).
        """
        projected = self._project(camera)
        if projected.means2d.requires_grad:
            projected.means2d.retain_grad()
        raw_colors = self._visible_raw_colors(projected, camera)
        visible = raw_colors.shape[0]
        if self.environment is not None:
            raw_colors = torch.cat([raw_colors, background_rows(self.environment, camera)])
        extras: dict[str, Any] = {"projected": projected}

        def composite(values: Tensor) -> Tensor:
            """values [rows, C] -> image [H, W, C]; leaves alpha (the Gaussians' coverage) in extras."""
            image, extras["alpha"] = rasterize(projected, values[:visible])
            if values.shape[0] > visible:
                image = image + (1 - extras["alpha"]) * values[visible:].reshape(camera.height, camera.width, -1)
            return image

        def render_depth() -> Tensor:
            """Expected depth of the visible surface [H, W, 1], 0 where nothing was hit."""
            depths = projected.depths[:, None]
            if self.sky is None:
                depth, alpha = rasterize(projected, depths)
            else:  # the scene's Gaussians only: the sky stands for infinity
                scene = (projected.index < self.num_gaussians).to(depths.dtype)[:, None]
                both, _ = rasterize(projected, torch.cat([depths * scene, scene], -1))
                depth, alpha = both.split(1, -1)
            return depth / alpha.clamp_min(1e-6)

        extras["render_depth"] = render_depth
        return LdrFeatures(
            colors=(raw_colors + 0.5).clamp_min(0), raw_colors=raw_colors, composite=composite, extras=extras
        )

    def _project(self, camera: Camera):
        """The scene's Gaussians (then the sky's, when used) projected into `camera`.

        A refined pose (camera.c2w requires grad) reaches the C++ projection, which takes the pose
        as a constant, as the same rigid motion of every Gaussian instead (backbones.gs.rigid).
        """
        scales = torch.exp(self.log_scales.clamp(-20, 20))  # finite, so culled rows never see inf * 0
        means: Tensor = self.means
        quats: Tensor = self.quats
        opacities = torch.sigmoid(self.opacity_logits)
        if self.sky is not None:
            means, quats, scales, opacities = with_sky(self.sky, means, quats, scales, opacities)
        if camera.c2w.requires_grad:
            camera, motion = camera_as_world_motion(camera)
            means, quats = move_gaussians(means, quats, motion)
        return project_gaussians(means, quats, scales, opacities, camera, backend=self.config.backend)

    def _visible_raw_colors(self, projected, camera: Camera) -> Tensor:
        """Raw colours [V, 3] of the visible rows: the scene's by their SH, seen from `camera`'s centre
        (the refined one, differentiable, when poses are refined), the sky's own."""
        scene_visible = projected.index.shape[0] if self.sky is None else scene_rows(projected, self.num_gaussians)
        index = projected.index[:scene_visible]
        degree, backend = self.active_sh_degree, self.config.backend
        raw = visible_colors(degree, self.sh_dc, self.sh_rest, self.means, index, camera.center, backend=backend)
        if self.sky is not None:
            raw = torch.cat([raw, self.sky.colors[projected.index[scene_visible:] - self.num_gaussians]])
        return raw

    @property
    def coarse_to_fine_pays(self) -> bool:
        """Measured with the budgeted MCMC recipe (docs/sizes.md); the paper's clone/split/prune recipe
        trains at full size, as the official code does."""
        return isinstance(self.config.strategy, McmcStrategy)

    def set_image_scale(self, scale: float) -> None:
        """A coarse level has scale^2 of the pixels: grow to that share of the budget (the Gaussians
        already there stay; growth resumes as the images get finer)."""
        self.budget = max(1, int(self.full_budget * scale * scale))

    @torch.no_grad()
    def after_step(self, step: int, features: LdrFeatures, optimizer: torch.optim.Optimizer) -> None:
        """Raise the SH degree on schedule (never lowered when the run length is re-estimated) and
        run the densification strategy (keeps Adam state aligned)."""
        interval = max(1, round(self.config.sh_increase_every * self.max_steps / REFERENCE_STEPS))
        self.active_sh_degree = max(self.active_sh_degree, min(self.config.sh_degree, (step + 1) // interval))
        projected = features.extras.get("projected")
        if projected is not None and self.sky is not None:
            projected = scene_projection(projected, self.num_gaussians)
        self.config.strategy.step_post_backward(
            self, optimizer, self.strategy_state, step, self.max_steps, projected, self.budget
        )

    def load_gaussians(self, tensors: dict[str, Tensor]) -> None:
        """Replace all Gaussians (e.g. from load_ply); rebuild the optimiser afterwards."""
        for name in GAUSSIAN_PARAMETERS:
            if name not in tensors:
                raise ValueError(f"missing {name!r}: pass the dict load_ply returns")
            setattr(self, name, nn.Parameter(tensors[name].float().clone()))
        self.strategy_state = self.config.strategy.initial_state(self.num_gaussians)

    def export_ply(self, path) -> Path:
        """Write the Gaussians as a standard 3DGS PLY (`mono-hdr export` looks for this method).

        The PLY holds the Gaussians only; an environment map goes beside it as `<name>.environment.exr`
        (lat-long raw values, see sky.environment_image), sky Gaussians as `<name>.sky.ply`."""
        written = export_ply(self, path)
        if self.environment is not None:
            export_environment(self.environment, written.with_suffix(".environment.exr"))
        if self.sky is not None:
            export_sky(self.sky, written.with_suffix(".sky.ply"))
        return written

    def get_extra_state(self) -> dict:
        """State outside the parameters that shapes renders and training: the active SH degree
        (a model loaded without it renders with degree 0) and the strategy's statistics."""
        return {
            "active_sh_degree": self.active_sh_degree,
            "strategy_state": {name: value.clone() for name, value in self.strategy_state.items()},
        }

    def set_extra_state(self, state: dict) -> None:
        self.active_sh_degree = int(state["active_sh_degree"])
        self.strategy_state = {name: value.clone() for name, value in state["strategy_state"].items()}

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # densification changes N: take the checkpoint's shapes before loading values
        for name in GAUSSIAN_PARAMETERS:
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
        d2 = torch.cdist(points[start : start + chunk], points).square()
        nearest = torch.topk(d2, k + 1, largest=False).values[:, 1:]  # drop the point itself
        result.append(nearest.mean(-1))
    return torch.cat(result).clamp_min(1e-7).sqrt()
