"""Adaptive density control of 3DGS (clone, split, prune, opacity reset) as a strategy object.

The strategy owns a small state (accumulated screen-space gradients, visibility counts, max
screen radii) and edits the Gaussians and the optimiser together, so Adam's moments always
line up row by row with the parameters they belong to.
"""

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from backbones.gs.reference import quaternion_to_rotation

# The schedule of the official 3DGS recipe, as fractions of its 30k steps.
REFERENCE_STEPS = 30_000


@dataclass
class DensityControlSchedule:
    """Step numbers of the density control for one run length."""

    refine_start: int
    refine_stop: int
    refine_every: int
    reset_every: int

    @classmethod
    def scaled(cls, max_steps: int, refine_start: int, refine_stop: int, refine_every: int,
               reset_every: int, min_refine_every: int) -> "DensityControlSchedule":
        """The 30k-step schedule given in steps, scaled to `max_steps`."""
        ratio = max_steps / REFERENCE_STEPS
        every = max(min_refine_every, round(refine_every * ratio))
        return cls(refine_start=round(refine_start * ratio), refine_stop=round(refine_stop * ratio),
                   refine_every=every, reset_every=max(every, round(reset_every * ratio)))


@dataclass
class DensityControlState:
    """Statistics gathered between two refinements, one row per Gaussian."""

    grad2d_sum: Tensor
    visible_count: Tensor
    max_radii: Tensor

    @classmethod
    def empty(cls, n: int) -> "DensityControlState":
        return cls(torch.zeros(n), torch.zeros(n), torch.zeros(n))


@dataclass
class DensityControl:
    """3DGS densification: clone small / split large Gaussians with high view-space gradient,
    prune transparent or oversized ones, periodically reset opacities.

    Works on a module holding nn.Parameters named in `param_names` (first dimension N) and
    an Adam optimiser whose param_groups carry the same "name"s.
    """

    schedule: DensityControlSchedule
    scene_extent: float
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    max_screen_size: float = 20.0
    max_gaussians: int = 1_000_000
    param_names: tuple[str, ...] = ("means", "sh_dc", "sh_rest", "log_scales", "quats", "opacity_logits")
    state: DensityControlState = field(default_factory=lambda: DensityControlState.empty(0))

    def step_post_backward(self, model, optimizer: torch.optim.Optimizer, step: int, means2d: Tensor,
                           radii: Tensor, width: int, height: int) -> None:
        """Accumulate this step's screen-space gradients, then refine/reset when scheduled.

        means2d: [N, 2] tensor whose .grad holds d loss / d pixel position (None: no data).
        radii: [N] screen radii in pixels (0 = not visible).
        """
        n = model.means.shape[0]
        if self.state.grad2d_sum.shape[0] != n:
            self.state = DensityControlState.empty(n)
        if step >= self.schedule.refine_stop:
            return
        if means2d.grad is not None:
            visible = radii > 0
            # 3DGS thresholds the gradient in normalised device coordinates: pixels * size / 2
            grad_ndc = means2d.grad.detach() * torch.tensor([0.5 * width, 0.5 * height])
            self.state.grad2d_sum[visible] += grad_ndc[visible].norm(dim=-1)
            self.state.visible_count[visible] += 1
            self.state.max_radii[visible] = torch.maximum(self.state.max_radii[visible], radii[visible].float())
        if step > self.schedule.refine_start and step % self.schedule.refine_every == 0:
            self._grow(model, optimizer)
            self._prune(model, optimizer, prune_big=step > self.schedule.reset_every)
            self.state = DensityControlState.empty(model.means.shape[0])
        if step > 0 and step % self.schedule.reset_every == 0:
            self._reset_opacities(model, optimizer)

    def _grow(self, model, optimizer) -> None:
        average = self.state.grad2d_sum / self.state.visible_count.clamp_min(1)
        high = average > self.grad_threshold
        budget = self.max_gaussians - model.means.shape[0]
        if int(high.sum()) > budget:  # keep the strongest within the Gaussian budget
            keep = torch.zeros_like(high)
            if budget > 0:
                keep[torch.topk(torch.where(high, average, -1.0), budget).indices] = True
            high &= keep
        small = torch.exp(model.log_scales.detach()).amax(-1) <= self.percent_dense * self.scene_extent
        clone, split = high & small, high & ~small
        if clone.any():
            _edit_rows(model, optimizer, self.param_names,
                       lambda name, p: torch.cat([p, p[clone]]), lambda name, v: torch.cat([v, torch.zeros_like(v[clone])]))
            split = torch.cat([split, torch.zeros(int(clone.sum()), dtype=torch.bool)])
        if split.any():
            self._split(model, optimizer, split)

    def _split(self, model, optimizer, split: Tensor) -> None:
        """Replace each selected Gaussian by two samples from it, with scales divided by 1.6."""
        scales = torch.exp(model.log_scales.detach()[split]).repeat(2, 1)
        rotations = quaternion_to_rotation(model.quats.detach()[split]).repeat(2, 1, 1)
        offsets = (rotations @ (torch.randn_like(scales) * scales)[..., None]).squeeze(-1)
        new_rows = {
            "means": model.means.detach()[split].repeat(2, 1) + offsets,
            "log_scales": torch.log(scales / 1.6),
        }

        def edit(name, p):
            added = new_rows[name] if name in new_rows else p[split].repeat(2, *[1] * (p.dim() - 1))
            return torch.cat([p[~split], added])

        _edit_rows(model, optimizer, self.param_names, edit,
                   lambda name, v: torch.cat([v[~split], torch.zeros_like(v[split]).repeat(2, *[1] * (v.dim() - 1))]))

    def _prune(self, model, optimizer, prune_big: bool) -> None:
        n = model.means.shape[0]
        remove = torch.sigmoid(model.opacity_logits.detach()) < self.prune_opacity
        if prune_big:
            max_radii = torch.cat([self.state.max_radii, torch.zeros(n - self.state.max_radii.shape[0])])
            remove |= max_radii > self.max_screen_size
            remove |= torch.exp(model.log_scales.detach()).amax(-1) > 0.1 * self.scene_extent
        if remove.all():  # never prune to an empty model: keep the most opaque Gaussian
            remove[model.opacity_logits.detach().argmax()] = False
        if remove.any():
            _edit_rows(model, optimizer, self.param_names, lambda name, p: p[~remove], lambda name, v: v[~remove])

    def _reset_opacities(self, model, optimizer) -> None:
        """Clamp opacities to <= 0.01 and forget their Adam moments, as 3DGS does."""
        ceiling = math.log(0.01 / 0.99)

        def edit(name, p):
            return p.clamp(max=ceiling) if name == "opacity_logits" else p

        def edit_state(name, v):
            return torch.zeros_like(v) if name == "opacity_logits" else v

        _edit_rows(model, optimizer, ("opacity_logits",), edit, edit_state)


def _edit_rows(model, optimizer, names, edit_param, edit_state) -> None:
    """Swap each named parameter for edit_param(name, data) and its Adam moments for
    edit_state(name, moment), keeping the optimiser's per-parameter state attached."""
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
                    state[key] = edit_state(name, state[key])
            optimizer.state[new] = state
        group["params"][0] = new
        setattr(model, name, new)
    for name in names:  # parameters the optimiser does not hold (frozen) still change shape
        current = getattr(model, name)
        if not any(current is p for g in optimizer.param_groups for p in g["params"]):
            setattr(model, name, torch.nn.Parameter(edit_param(name, current.detach()),
                                                    requires_grad=current.requires_grad))
