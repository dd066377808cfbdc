"""Densification strategies of the 3DGS backbone, as gsplat structures them.

A strategy is a config dataclass (its fields are the `--backbone.strategy.*` flags) whose
methods edit the Gaussian parameters of a module and the optimiser's Adam moments together,
so moments always line up row by row with the parameters they belong to. What a strategy
gathers between refinements lives in a small state dict of tensors that the backbone keeps
and saves (get_extra_state). Step numbers are given for a 30k-step run and scaled to the run
length each time they are read, so a re-estimated run length (--max-seconds) rescales them
without touching the state.

- `McmcStrategy` (the CPU default): 3DGS as Markov chain Monte Carlo (Kheradmand et al.,
  NeurIPS 2024), as gsplat's MCMCStrategy does it: dead Gaussians are relocated onto live
  ones, new ones are added up to a budget, positions get noise scaled by the position
  learning rate, and opacity and scale regularisers keep the set lean. The budget makes the
  step cost predictable.
- `DefaultStrategy` (the paper recipe): the official clone / split / prune rules with
  periodic opacity resets.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import ClassVar

import torch
from torch import Tensor

from backbones.gs.reference import quaternion_to_rotation
from mono_hdr_plugin.core.validation import NON_NEGATIVE, POSITIVE, at_least, between

GAUSSIAN_PARAMETERS = ("means", "sh_dc", "sh_rest", "log_scales", "quats", "opacity_logits")
"""The per-Gaussian parameters of the backbone, first dimension N, in optimiser-group order."""
REFERENCE_STEPS = 30_000
"""Strategies give step numbers for a run of this length; they are scaled to the actual run."""


@dataclass(frozen=True)
class RefineSchedule:
    """When a strategy refines, for one run length."""

    start: int
    stop: int
    every: int

    @classmethod
    def scaled(cls, max_steps: int, start: int, stop: int, every: int, min_every: int) -> "RefineSchedule":
        """The 30k-step schedule given in steps, scaled to `max_steps`."""
        ratio = max_steps / REFERENCE_STEPS
        return cls(start=round(start * ratio), stop=round(stop * ratio), every=max(min_every, round(every * ratio)))

    def due(self, step: int) -> bool:
        return self.start < step < self.stop and step % self.every == 0


def with_shared_rows(name: str, value: Tensor, sources: Tensor, logits: Tensor, log_scales: Tensor) -> Tensor:
    """A copy of parameter `name` whose `sources` rows take the opacity and scale they will share
    with their copies (other parameters are copied unchanged)."""
    value = value.clone()
    if name == "opacity_logits":
        value[sources] = logits
    elif name == "log_scales":
        value[sources] = log_scales
    return value


@dataclass
class McmcStrategy:
    """3DGS-MCMC: relocate dead Gaussians onto live ones, grow up to a budget, explore with
    position noise; opacity and scale regularisers (gsplat's MCMCStrategy)."""

    max_gaussians: int | None = None
    """Gaussian budget; None: gaussians_per_pixel times the pixels of all training views."""
    gaussians_per_pixel: float = 0.1
    """Budget per training pixel (pixels per view x views) when max_gaussians is not given."""
    grow_fraction: float = 0.05
    """Each refinement adds this fraction of the current count, up to the budget."""
    refine_start: int = 500
    """First refinement, in steps of a 30k-step run (scaled to the run length)."""
    refine_stop: int = 25_000
    """No refinement from this step of a 30k-step run on (scaled to the run length)."""
    refine_every: int = 100
    """Refine every this many steps of a 30k-step run (scaled to the run length)."""
    min_refine_every: int = 10
    """Lower bound on the scaled refinement interval."""
    min_opacity: float = 0.005
    """Gaussians at or below this opacity are dead: refinement relocates them."""
    noise_lr: float = 5e5
    """Position noise scale, times the current position learning rate and the covariance."""
    opacity_reg: float = 0.01
    """Weight of the mean opacity in the loss."""
    scale_reg: float = 0.01
    """Weight of the mean scale (scene units) in the loss."""

    flag_rules: ClassVar = {
        "max_gaussians": at_least(1),
        "gaussians_per_pixel": POSITIVE,
        "grow_fraction": NON_NEGATIVE,
        "refine_start": NON_NEGATIVE,
        "refine_stop": NON_NEGATIVE,
        "refine_every": at_least(1),
        "min_refine_every": at_least(1),
        "min_opacity": between(0, 1, high_open=True),
        "noise_lr": NON_NEGATIVE,
        "opacity_reg": NON_NEGATIVE,
        "scale_reg": NON_NEGATIVE,
    }

    def budget(self, training_pixels: int) -> int:
        """The most Gaussians this strategy ever holds, for `training_pixels` pixels of training views."""
        if self.max_gaussians is not None:
            if self.max_gaussians < 1:
                raise ValueError(f"--backbone.strategy.max-gaussians must be >= 1, got {self.max_gaussians}")
            return self.max_gaussians
        if not self.gaussians_per_pixel > 0:
            raise ValueError(f"--backbone.strategy.gaussians-per-pixel must be > 0, got {self.gaussians_per_pixel}")
        return max(1, int(self.gaussians_per_pixel * training_pixels))

    def schedule(self, max_steps: int) -> RefineSchedule:
        return RefineSchedule.scaled(
            max_steps, self.refine_start, self.refine_stop, self.refine_every, self.min_refine_every
        )

    def initial_state(self, n: int) -> dict[str, Tensor]:
        """MCMC gathers no per-Gaussian statistics."""
        return {}

    def regularisation(self, model) -> dict[str, Tensor]:
        """Loss terms: mean opacity and mean scale, weighted."""
        terms = {}
        if self.opacity_reg > 0:
            terms["opacity_reg"] = self.opacity_reg * torch.sigmoid(model.opacity_logits).mean()
        if self.scale_reg > 0:
            terms["scale_reg"] = self.scale_reg * torch.exp(model.log_scales.clamp(-20, 20)).mean()
        return terms

    @torch.no_grad()
    def step_post_backward(
        self,
        model,
        optimizer: torch.optim.Optimizer,
        state: dict[str, Tensor],
        step: int,
        max_steps: int,
        projected,
        budget: int,
    ) -> None:
        """After the optimiser step: refine when scheduled, then add position noise."""
        if self.schedule(max_steps).due(step):
            self.relocate(model, optimizer)
            self.grow(model, optimizer, budget)
        means_lr = next(group["lr"] for group in optimizer.param_groups if group.get("name") == "means")
        self.add_position_noise(model, means_lr)

    @torch.no_grad()
    def relocate(self, model, optimizer: torch.optim.Optimizer) -> int:
        """Move every dead Gaussian onto a live one drawn by opacity; both share the opacity and
        shrink their scale so that together they render as the one did. Returns the number moved."""
        opacities = torch.sigmoid(model.opacity_logits)
        dead = opacities <= self.min_opacity
        alive = (~dead).nonzero().squeeze(1)
        dead_rows = dead.nonzero().squeeze(1)
        if dead_rows.numel() == 0 or alive.numel() == 0:
            return 0
        sources = alive[torch.multinomial(opacities[alive], dead_rows.numel(), replacement=True)]
        new_logits, new_log_scales = self._shared_rows(model, sources)
        targets = torch.cat([sources, dead_rows])

        def edit(name: str, value: Tensor) -> Tensor:
            value = with_shared_rows(name, value, sources, new_logits, new_log_scales)
            value[dead_rows] = value[sources]
            return value

        def edit_moment(name: str, moment: Tensor) -> Tensor:
            moment = moment.clone()
            moment[targets] = 0  # both halves start afresh, as new Gaussians do
            return moment

        edit_gaussians(model, optimizer, GAUSSIAN_PARAMETERS, edit, edit_moment)
        return dead_rows.numel()

    @torch.no_grad()
    def grow(self, model, optimizer: torch.optim.Optimizer, budget: int) -> int:
        """Add grow_fraction more Gaussians (at most up to the budget), each a copy of one drawn by
        opacity that shares its opacity and scale with it. Returns the number added."""
        count = model.means.shape[0]
        added = min(budget, int((1 + self.grow_fraction) * count)) - count
        if added <= 0:
            return 0
        opacities = torch.sigmoid(model.opacity_logits)
        if not opacities.sum() > 0:  # every opacity underflowed: draw uniformly instead
            opacities = torch.ones_like(opacities)
        sources = torch.multinomial(opacities, added, replacement=True)
        new_logits, new_log_scales = self._shared_rows(model, sources)

        def edit(name: str, value: Tensor) -> Tensor:
            value = with_shared_rows(name, value, sources, new_logits, new_log_scales)
            return torch.cat([value, value[sources]])

        def edit_moment(name: str, moment: Tensor) -> Tensor:
            return torch.cat([moment, moment.new_zeros(added, *moment.shape[1:])])

        edit_gaussians(model, optimizer, GAUSSIAN_PARAMETERS, edit, edit_moment)
        return added

    def _shared_rows(self, model, sources: Tensor) -> tuple[Tensor, Tensor]:
        """Opacity logits and log scales for Gaussians that are copied (sources may repeat: a
        Gaussian drawn k times ends up as k + 1 copies)."""
        copies = torch.bincount(sources, minlength=model.means.shape[0])[sources] + 1
        opacities = torch.sigmoid(model.opacity_logits[sources])
        scales = torch.exp(model.log_scales[sources])
        new_opacities, new_scales = relocation(opacities, scales, copies)
        new_opacities = new_opacities.clamp(self.min_opacity, 1.0 - torch.finfo(torch.float32).eps)
        return torch.logit(new_opacities), torch.log(new_scales)

    @torch.no_grad()
    def add_position_noise(self, model, means_lr: float) -> None:
        """means += Sigma @ n * lr * noise_lr * g(opacity), n ~ N(0, I): Gaussians near death wander,
        opaque ones (g ~ 0 above opacity ~0.1) stay. Only rows whose gate is not negligible are drawn."""
        opacities = torch.sigmoid(model.opacity_logits)
        gate = torch.sigmoid(100.0 * ((1.0 - opacities) - 0.995))
        rows = (gate > 1e-6).nonzero().squeeze(1)
        if rows.numel() == 0:
            return
        rotation = quaternion_to_rotation(model.quats[rows])
        scales = torch.exp(model.log_scales[rows].clamp(-20, 20))
        covariance = (rotation * scales[:, None, :] ** 2) @ rotation.transpose(1, 2)
        noise = torch.randn(rows.numel(), 3) * (gate[rows] * means_lr * self.noise_lr)[:, None]
        model.means.index_add_(0, rows, (covariance @ noise[..., None]).squeeze(-1))


@lru_cache(maxsize=1)
def _relocation_coefficients(max_copies: int = 51) -> Tensor:
    """coefficients[c - 1, k] = sum_{i=k+1}^{c} binom(i - 1, k) (-1)^k / sqrt(k + 1), float64."""
    table = torch.zeros(max_copies, max_copies, dtype=torch.float64)
    for copies in range(1, max_copies + 1):
        for k in range(copies):
            table[copies - 1, k] = (
                sum(math.comb(i - 1, k) for i in range(k + 1, copies + 1)) * (-1) ** k / math.sqrt(k + 1)
            )
    return table


def relocation(opacities: Tensor, scales: Tensor, copies: Tensor) -> tuple[Tensor, Tensor]:
    """Opacity and scale of each of `copies` Gaussians that together render like one Gaussian of
    `opacities` [M] and `scales` [M, 3] (3DGS-MCMC, eq. 9): o' = 1 - (1 - o)^(1/c) and
    s' = s * o / sum_{i=1}^{c} sum_{k=0}^{i-1} binom(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1).
    Copies above 51 are treated as 51 (gsplat's table size)."""
    table = _relocation_coefficients()
    copies = copies.clamp(1, table.shape[0]).long()
    o = opacities.double()
    new_o = 1.0 - torch.pow(1.0 - o, 1.0 / copies.double())
    powers = new_o[:, None] ** torch.arange(1, table.shape[0] + 1, dtype=torch.float64)
    denominator = (table[copies - 1] * powers).sum(-1)
    return new_o.to(opacities.dtype), (scales.double() * (o / denominator)[:, None]).to(scales.dtype)


def ndc_gradient_scale(projected) -> Tensor:
    """[2] factors taking d loss / d pixel position to the gradient 3DGS thresholds: in normalised device
    coordinates of the whole frame (pixels * size / 2), of a loss averaged over the whole frame.

    A crop (region training, Camera.crop) renders w x h of a W x H frame: NDC spans the frame, so the
    factors are W / 2 and H / 2, not w / 2 and h / 2; and the step's loss is a mean over the crop's w * h
    pixels, each weighted W * H / (w * h) times more than in a whole-frame mean, which w * h / (W * H)
    undoes. A Gaussian inside the crop then accumulates what a whole-image step would have given it
    (tests/gs/test_gs_regions.py), and a crop does not move the densification threshold.
    """
    frame_width, frame_height = projected.frame or (projected.width, projected.height)
    share = projected.width * projected.height / (frame_width * frame_height)
    return torch.tensor([0.5 * frame_width * share, 0.5 * frame_height * share])


@dataclass
class DefaultStrategy:
    """The official 3DGS density control: clone small / split large Gaussians whose view-space
    gradient is high, prune transparent or oversized ones, reset opacities periodically."""

    max_gaussians: int = 300_000
    """Stop growing beyond this many Gaussians (a CPU memory and time guard)."""
    refine_start: int = 500
    """First densification, in steps of a 30k-step run (scaled to the run length)."""
    refine_stop: int = 15_000
    """No densification from this step of a 30k-step run on (scaled to the run length)."""
    refine_every: int = 100
    """Densify every this many steps of a 30k-step run (scaled to the run length)."""
    min_refine_every: int = 10
    """Lower bound on the scaled interval, so short runs still average gradients over views."""
    reset_opacity_every: int = 3000
    """Reset opacities every this many steps of a 30k-step run (scaled to the run length)."""
    grad_threshold: float = 2e-4
    """Densify Gaussians whose mean view-space gradient (NDC units) exceeds this."""
    percent_dense: float = 0.01
    """Gaussians larger than this fraction of the scene extent are split, smaller ones cloned."""
    prune_opacity: float = 0.005
    """Prune Gaussians less opaque than this."""
    max_screen_size: float = 20.0
    """After the first opacity reset, prune Gaussians wider than this many pixels."""

    flag_rules: ClassVar = {
        "max_gaussians": at_least(1),
        "refine_start": NON_NEGATIVE,
        "refine_stop": NON_NEGATIVE,
        "refine_every": at_least(1),
        "min_refine_every": at_least(1),
        "reset_opacity_every": at_least(1),
        "grad_threshold": NON_NEGATIVE,
        "percent_dense": POSITIVE,
        "prune_opacity": between(0, 1, high_open=True),
        "max_screen_size": POSITIVE,
    }

    def budget(self, training_pixels: int) -> int:
        if self.max_gaussians < 1:
            raise ValueError(f"--backbone.strategy.max-gaussians must be >= 1, got {self.max_gaussians}")
        return self.max_gaussians

    def schedule(self, max_steps: int) -> RefineSchedule:
        return RefineSchedule.scaled(
            max_steps, self.refine_start, self.refine_stop, self.refine_every, self.min_refine_every
        )

    def reset_every(self, max_steps: int) -> int:
        return max(self.schedule(max_steps).every, round(self.reset_opacity_every * max_steps / REFERENCE_STEPS))

    def initial_state(self, n: int) -> dict[str, Tensor]:
        """Per Gaussian, since the last refinement: summed view-space gradient norms, the number
        of views that saw it, and its largest screen radius."""
        return {"grad2d_sum": torch.zeros(n), "visible_count": torch.zeros(n), "max_radii": torch.zeros(n)}

    def regularisation(self, model) -> dict[str, Tensor]:
        return {}

    @torch.no_grad()
    def step_post_backward(
        self,
        model,
        optimizer: torch.optim.Optimizer,
        state: dict[str, Tensor],
        step: int,
        max_steps: int,
        projected,
        budget: int,
    ) -> None:
        """Accumulate this step's screen-space gradients, then refine/reset when scheduled.

        projected: the step's ProjectedGaussians, whose means2d.grad holds d loss / d pixel
        position of the visible Gaussians (None: no data this step).
        """
        n = model.means.shape[0]
        if state["grad2d_sum"].shape[0] != n:
            state.update(self.initial_state(n))
        schedule = self.schedule(max_steps)
        if step >= schedule.stop:
            return
        if projected is not None and projected.means2d.grad is not None:
            index = projected.index
            scale = ndc_gradient_scale(projected)
            state["grad2d_sum"].index_add_(0, index, (projected.means2d.grad * scale).norm(dim=-1))
            state["visible_count"].index_add_(0, index, torch.ones(index.shape[0]))
            state["max_radii"][index] = torch.maximum(state["max_radii"][index], projected.radii[index].float())
        reset_every = self.reset_every(max_steps)
        if schedule.due(step):
            self._grow(model, optimizer, state, budget)
            self._prune(model, optimizer, state, prune_big=step > reset_every)
            state.update(self.initial_state(model.means.shape[0]))
        if step > 0 and step % reset_every == 0:
            self._reset_opacities(model, optimizer)

    def _grow(self, model, optimizer, state, budget: int) -> None:
        average = state["grad2d_sum"] / state["visible_count"].clamp_min(1)
        high = average > self.grad_threshold
        room = budget - model.means.shape[0]
        if int(high.sum()) > room:  # keep the strongest within the Gaussian budget
            keep = torch.zeros_like(high)
            if room > 0:
                keep[torch.topk(torch.where(high, average, -1.0), room).indices] = True
            high &= keep
        scene_extent = model.scene_extent
        small = torch.exp(model.log_scales).amax(-1) <= self.percent_dense * scene_extent
        clone, split = high & small, high & ~small
        if clone.any():
            edit_gaussians(
                model,
                optimizer,
                GAUSSIAN_PARAMETERS,
                lambda name, p: torch.cat([p, p[clone]]),
                lambda name, v: torch.cat([v, torch.zeros_like(v[clone])]),
            )
            split = torch.cat([split, torch.zeros(int(clone.sum()), dtype=torch.bool)])
        if split.any():
            self._split(model, optimizer, split)

    def _split(self, model, optimizer, split: Tensor) -> None:
        """Replace each selected Gaussian by two samples from it, with scales divided by 1.6."""
        scales = torch.exp(model.log_scales[split]).repeat(2, 1)
        rotations = quaternion_to_rotation(model.quats[split]).repeat(2, 1, 1)
        offsets = (rotations @ (torch.randn_like(scales) * scales)[..., None]).squeeze(-1)
        new_rows = {"means": model.means[split].repeat(2, 1) + offsets, "log_scales": torch.log(scales / 1.6)}

        def edit(name, p):
            added = new_rows[name] if name in new_rows else p[split].repeat(2, *[1] * (p.dim() - 1))
            return torch.cat([p[~split], added])

        edit_gaussians(
            model,
            optimizer,
            GAUSSIAN_PARAMETERS,
            edit,
            lambda name, v: torch.cat([v[~split], torch.zeros_like(v[split]).repeat(2, *[1] * (v.dim() - 1))]),
        )

    def _prune(self, model, optimizer, state, prune_big: bool) -> None:
        n = model.means.shape[0]
        remove = torch.sigmoid(model.opacity_logits) < self.prune_opacity
        if prune_big:
            max_radii = torch.cat([state["max_radii"], torch.zeros(n - state["max_radii"].shape[0])])
            remove |= max_radii > self.max_screen_size
            remove |= torch.exp(model.log_scales).amax(-1) > 0.1 * model.scene_extent
        if remove.all():  # never prune to an empty model: keep the most opaque Gaussian
            remove[model.opacity_logits.argmax()] = False
        if remove.any():
            edit_gaussians(
                model, optimizer, GAUSSIAN_PARAMETERS, lambda name, p: p[~remove], lambda name, v: v[~remove]
            )

    def _reset_opacities(self, model, optimizer) -> None:
        """Clamp opacities to <= 0.01 and forget their Adam moments, as 3DGS does."""
        ceiling = math.log(0.01 / 0.99)
        edit_gaussians(
            model,
            optimizer,
            ("opacity_logits",),
            lambda name, p: p.clamp(max=ceiling),
            lambda name, v: torch.zeros_like(v),
        )


Strategy = McmcStrategy | DefaultStrategy


def edit_gaussians(
    model,
    optimizer: torch.optim.Optimizer,
    names: tuple[str, ...],
    edit_param: Callable[[str, Tensor], Tensor],
    edit_moment: Callable[[str, Tensor], Tensor],
) -> None:
    """Swap each named parameter of `model` for edit_param(name, data) and its Adam moments for
    edit_moment(name, moment), keeping the optimiser's per-parameter state attached."""
    for group in optimizer.param_groups:
        name = group.get("name")
        if name not in names:
            continue
        (old,) = group["params"]
        new = torch.nn.Parameter(edit_param(name, old.detach()), requires_grad=old.requires_grad)
        state = optimizer.state.pop(old, None)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                if key in state:
                    state[key] = edit_moment(name, state[key])
            optimizer.state[new] = state
        group["params"][0] = new
        setattr(model, name, new)
    held = {id(p) for group in optimizer.param_groups for p in group["params"]}
    for name in names:  # parameters the optimiser does not hold (frozen) still change shape
        current = getattr(model, name)
        if id(current) not in held:
            setattr(
                model, name, torch.nn.Parameter(edit_param(name, current.detach()), requires_grad=current.requires_grad)
            )
