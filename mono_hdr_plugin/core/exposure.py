"""Exposure per view: the times a capture knows, corrections learned where it does not, and the
brightness at which Mono-HDR's LDR branch renders each view.

A camera on auto-exposure changes its exposure from photo to photo, and photos without EXIF
carry none. `ViewExposures` holds, for every training view, its log exposure relative to one
reference view: ln(t_i / t_ref) from the data, plus a learned correction when exposures are
learned (the reference view's is fixed at 0, so the scale stays the data's). Where the data has
no time, the starting value is measured from the photos: the structure-from-motion points seen
by several views, linearised through the response, give each view's brightness ratio (a
two-way median over points and views, so occlusions and highlights do not count).

- Methods that take exposure (the HDR-NeRF / HDR-GS baselines) render view i at
  t_ref * exp(log relative exposure): their CRF sees the corrected ln dt.
- Mono-HDR (and its ablations) renders one canonical LDR image, the one the reference
  exposure gives; the per-view brightness term turns it into view i's photo through the
  camera's response f: LDR_i = f(exp(b_i) f^-1(LDR)), clipped at white. f is the curve
  process-data recovered from the brackets (camera_response.json), else sRGB.

`--learn-exposure` turns learning on; by default it is on when the data's exposures are unknown
(`exposures.json` holds null), and the term is used whenever the training views' exposures
differ or are learned. The learned values are written to OUT/learned_exposures.json.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar, Literal

import numpy as np
import torch
from torch import Tensor, nn

from mono_hdr_plugin.core.colour import decode_curve
from mono_hdr_plugin.core.configs import ABSENT_IN_SAVED_CONFIG
from mono_hdr_plugin.core.validation import NON_NEGATIVE, POSITIVE
from mono_hdr_plugin.core.white_balance import ViewWhiteBalance

RESPONSE_LEVELS = 256
FIT_RANGE_STOPS = 10.0
"""A test view with unknown exposure is fitted within this many stops of the reference."""
FIT_ITERATIONS = 40


@dataclass
class ExposureConfig:
    """Exposure of each training view: known from the data, or learned."""

    learn_exposure: bool | None = None
    """Learn each training view's exposure (log scale, one reference view fixed) jointly with the
    model. Default: on when the data's exposures are unknown (process-data found none)."""
    exposure_lr: float = 0.001
    """Adam learning rate of the learned log exposures. Adam moves each one by about this much every
    step whatever the size of its gradient, so once an exposure is right it random-walks by about
    lr x sqrt(steps), and a start that is off by up to e^(lr x steps) is still corrected. How far
    each rate let good exposures drift: docs/own_photos.md, "Exposure per view in training"."""

    learn_white_balance: Literal["auto", "on", "off"] = field(
        default="auto",
        metadata={ABSENT_IN_SAVED_CONFIG: "off"},  # runs before it learned no gains
    )
    """Learn three gains per training view (core.white_balance), applied with the exposure. auto: on
    where exposures are learned, or the photos' EXIF says the camera balanced white itself (process-
    data records it); off for the studio and the paper's datasets, whose photos share one balance."""
    white_balance_lr: float = 0.001
    """Adam learning rate of the learned log gains (as --exposure-lr: about this much a step)."""
    white_balance_pull: float = 1e-4
    """Weight of the L2 pull of each view's log gains toward the mean balance of the views: weak, so
    it decides only for a view whose photo says little (at 0.01 it held a toy scene's gains at a tenth
    of their true size: tests/core/test_white_balance.py)."""
    eval_appearance: Literal["auto", "on", "off"] = "auto"
    """Also score held-out views with their appearance fitted: exposure and white balance fitted on
    the left half of the photo, PSNR/SSIM on the right half (metrics.json `appearance_protocol`).
    auto: on when the run learns exposure or white balance (the held-out views' are then unknown)."""

    flag_rules: ClassVar = {
        "exposure_lr": POSITIVE,
        "white_balance_lr": POSITIVE,
        "white_balance_pull": NON_NEGATIVE,
    }


def srgb_response() -> np.ndarray:
    """The sRGB curve as a response table [256, 3]: code value k / 255 -> linear exposure."""
    return np.stack([decode_curve(np.linspace(0.0, 1.0, RESPONSE_LEVELS), "srgb")] * 3, -1)


def decode(code: Tensor, response: Tensor) -> Tensor:
    """Code values [..., 3] in [0, 1] -> linear exposure, interpolating the response table [256, 3]."""
    position = code.clamp(0.0, 1.0) * (RESPONSE_LEVELS - 1)
    low = position.detach().floor().clamp(max=RESPONSE_LEVELS - 2).long()
    fraction = position - low
    channels = torch.arange(3, device=code.device)
    return response[low, channels] * (1 - fraction) + response[low + 1, channels] * fraction


def encode(linear: Tensor, response: Tensor) -> Tensor:
    """Linear exposure [..., 3] -> code values in [0, 1] (the inverse of `decode`; white above 1)."""
    linear = linear.clamp(0.0, 1.0)
    codes = []
    for channel in range(3):
        table = response[:, channel].contiguous()
        values = linear[..., channel].contiguous()
        low = (torch.searchsorted(table, values.detach()) - 1).clamp(0, RESPONSE_LEVELS - 2)
        fraction = (values - table[low]) / (table[low + 1] - table[low])
        codes.append((low + fraction) / (RESPONSE_LEVELS - 1))
    return torch.stack(codes, -1).clamp(0.0, 1.0)


def brighten(ldr: Tensor, log_scale: Tensor, response: Tensor) -> Tensor:
    """The photo a camera with `response` takes with exp(log_scale) times the light of the one that
    gave `ldr` (one scale, or [3] per channel: exposure times white balance gains)."""
    return encode(decode(ldr, response) * torch.exp(log_scale), response)


def fit_log_relative(ldr: Tensor, image: Tensor, response: Tensor) -> Tensor:
    """The brightness (log relative exposure) that makes the reference-exposure `ldr` best match
    `image` (mean squared error, golden-section search): for views whose exposure is unknown."""
    return golden_section(lambda value: torch.mean((brighten(ldr, value, response) - image) ** 2), torch.zeros(()))


def fit_log_scales(ldr: Tensor, image: Tensor, response: Tensor) -> Tensor:
    """[3] the per-channel brightness (log exposure plus log gain) that makes the reference-exposure
    `ldr` best match `image`: a held-out view's exposure and white balance. The response acts on
    each channel alone, so each channel's scale is its own one-dimensional search."""

    def error(values: Tensor) -> Tensor:
        return torch.mean(((brighten(ldr, values, response) - image) ** 2).reshape(-1, 3), 0)

    return golden_section(error, torch.zeros(3))


class ViewExposures(nn.Module):
    """Per training view: log exposure relative to the reference view, a starting value plus a learned correction.

    initial_log [V]: ln(t_i / t_ref) from the data, or measured from the photos where unknown;
    correction: one learned scalar per view (zeros, frozen unless learning; one tensor each, so
    Adam leaves the views a step does not see alone); reference: the view whose correction stays 0;
    reference_exposure: t_ref in seconds; response [256, 3]: the camera's response table.
    """

    initial_log: Tensor
    reference: Tensor
    reference_exposure: Tensor
    response: Tensor

    def __init__(
        self,
        initial_log: Tensor,
        reference: int,
        reference_exposure: float,
        response: np.ndarray,
        learn: bool,
        learning_rate: float = 0.01,
        names: list[str] | None = None,
        known: bool = True,
        white_balance: ViewWhiteBalance | None = None,
    ):
        super().__init__()
        self.register_buffer("initial_log", initial_log.float())
        self.register_buffer("reference", torch.tensor(reference))
        self.register_buffer("reference_exposure", torch.tensor(float(reference_exposure)))
        self.register_buffer("response", torch.as_tensor(response, dtype=torch.float32))
        self.correction = nn.ParameterList(
            nn.Parameter(torch.zeros(()), requires_grad=learn) for _ in range(len(initial_log))
        )
        self.lr = learning_rate
        self.names = names or [str(i) for i in range(len(initial_log))]
        self.known = known  # whether the data gave exposure times (else t_ref is a placeholder)
        self.white_balance = white_balance

    @classmethod
    def from_state_dict(cls, state: dict[str, Tensor], prefix: str = "exposures.") -> "ViewExposures | None":
        """An empty module shaped like the one saved under `prefix` (None when there is none)."""
        if f"{prefix}initial_log" not in state:
            return None
        return cls(
            torch.zeros_like(state[f"{prefix}initial_log"]),
            0,
            1.0,
            state[f"{prefix}response"].numpy(),
            learn=False,
            white_balance=ViewWhiteBalance.from_state_dict(state, f"{prefix}white_balance."),
        )

    @property
    def learned(self) -> bool:
        """Whether the exposures are learned (the white balance, where there is one, always is)."""
        return self.correction[0].requires_grad

    @property
    def appearance_learned(self) -> bool:
        """Whether anything of a view's appearance is learned: a held-out view's is then unknown."""
        return self.learned or self.white_balance is not None

    def log_relative(self, view: int | None = None, exposure: float | None = None) -> Tensor:
        """ln(t / t_ref) of training view `view` (starting value plus learned), or of `exposure` seconds."""
        if view is None:
            if exposure is None:
                raise TypeError("log_relative needs a training view or an exposure in seconds")
            return torch.log(torch.tensor(float(exposure)) / self.reference_exposure)
        if view == int(self.reference):
            return self.initial_log[view]
        return self.initial_log[view] + self.correction[view]

    def relative_exposures(self) -> Tensor:
        """[V] t_i / t_ref of every training view, as the model now sees them."""
        with torch.no_grad():
            return torch.exp(torch.stack([self.log_relative(view) for view in range(len(self.correction))]))

    def log_scale(self, view: int | None = None, exposure: float | None = None) -> Tensor:
        """The log of the light a view's photo records relative to the canonical image: its log relative
        exposure (`log_relative`), plus its [3] log gains where white balance is learned."""
        log_relative = self.log_relative(view, exposure)
        if self.white_balance is None:
            return log_relative
        return log_relative + self.white_balance.log_gains(view)

    def brighten(self, ldr: Tensor, log_scale: Tensor) -> Tensor:
        """`brighten` through this capture's response."""
        return brighten(ldr, log_scale, self.response)

    def parameter_groups(self) -> list[dict]:
        groups = [{"name": "exposures", "params": list(self.correction), "lr": self.lr}] if self.learned else []
        return groups + ([] if self.white_balance is None else self.white_balance.parameter_groups())

    def learning_rate(self, group_name: str, step: int, base_lr: float) -> float:
        return base_lr

    def regularisation(self) -> dict[str, Tensor]:
        return {} if self.white_balance is None else self.white_balance.regularisation()

    def report(self) -> dict:
        """What OUT/learned_exposures.json holds: per training view, its exposure relative to the
        reference view, and in seconds when the data gave the reference's time."""
        relative = self.relative_exposures().tolist()
        initial = torch.exp(self.initial_log).tolist()
        reference_time = float(self.reference_exposure) if self.known else None
        return {
            "reference": self.names[int(self.reference)],
            "learned": self.learned,
            "white_balance": None if self.white_balance is None else self.white_balance.report(),
            "reference_exposure": reference_time,
            "views": {
                name: {
                    "relative": value,
                    "initial": start,
                    "seconds": None if reference_time is None else value * reference_time,
                }
                for name, value, start in zip(self.names, relative, initial)
            },
        }


def golden_section(error: Callable[[Tensor], Tensor], start: Tensor) -> Tensor:
    """The log scale(s) shaped like `start` that minimise `error` (one error per element, each
    unimodal in its own scale) within FIT_RANGE_STOPS of 0, by golden-section search."""
    low = torch.full_like(start, -FIT_RANGE_STOPS * math.log(2), dtype=torch.float64)
    high = -low
    ratio = (math.sqrt(5) - 1) / 2
    for _ in range(FIT_ITERATIONS):
        left, right = high - ratio * (high - low), low + ratio * (high - low)
        left_better = error(left.float()) < error(right.float())
        high, low = torch.where(left_better, right, high), torch.where(left_better, low, left)
    return ((low + high) / 2).float()


def choose_reference(exposures: list[float], brightness: list[float]) -> int:
    """The training view with the median exposure (ties: the median brightness): the canonical LDR
    image is then a typical photo, with as little clipping either way as the capture allows.

    The one reference rule. Training fixes this view's exposure (ViewExposures) and the viewer,
    videos and exports show it as EV 0 (`training.frames.calibrate`): EV 0 must be the exposure
    the model is anchored at, so both use this rule (the viewer once took the lower middle of the
    distinct exposures, and showed EV 0 one stop off the anchor for an even count). The median is
    over the views, so a capture shot mostly at one exposure is anchored there; for an even count
    it is the upper of the two middle views (of 0.15, 0.3, 0.6, 1.2 s: 0.6 s), the brighter photo,
    whose shadows are less lost in noise, and the rule training has always used.
    """
    order = sorted(range(len(exposures)), key=lambda i: (exposures[i], brightness[i]))
    return order[len(order) // 2]


def reference_view(views) -> int:
    """Index of the reference view among training views (with .exposure and .image): `choose_reference`."""
    return choose_reference([view.exposure for view in views], [float(view.image.mean()) for view in views])


def photometric_log_exposures(
    views, points: Tensor, response: np.ndarray, reference: int, iterations: int = 10
) -> np.ndarray:
    """[V] ln(t_i / t_ref) measured from the photos: the points' linearised brightness in each view.

    Every point is projected into every view; a point counts only when its pixel in every view
    that sees it is neither near clipping nor near the noise floor (keeping a point's darker
    views where its brighter ones clip would favour pixels whose noise happened to be low, and
    compress the ratios; docs/own_photos.md, "Exposure per view in training"). Log brightness = view offset + point
    radiance is solved by a two-way median (Tukey's median polish), which occlusions and
    highlights do not move. A view that sees no usable point keeps 0.
    """
    positions = points.double().numpy()
    logs = np.full((len(views), len(positions)), np.nan)
    clipped = np.zeros(len(positions), bool)
    for row, view in enumerate(views):
        camera = view.camera
        local = positions @ camera.w2c[:3, :3].double().numpy().T + camera.w2c[:3, 3].double().numpy()
        depth = local[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            cols = np.floor(camera.fx * local[:, 0] / depth + camera.cx)
            rows = np.floor(camera.fy * local[:, 1] / depth + camera.cy)
        seen = (depth > 0) & (cols >= 0) & (cols < camera.width) & (rows >= 0) & (rows < camera.height)
        code = view.image.numpy()[rows[seen].astype(int), cols[seen].astype(int)]
        usable = (code.max(-1) < 0.95) & (code.mean(-1) > 0.1)
        clipped[np.flatnonzero(seen)[~usable]] = True
        linear = decode(torch.from_numpy(code[usable]), torch.as_tensor(response, dtype=torch.float32)).numpy()
        logs[row, np.flatnonzero(seen)[usable]] = np.log(linear.mean(-1))
    offsets = np.zeros(len(views))
    shared = (np.isfinite(logs).sum(0) >= 2) & ~clipped
    logs = logs[:, shared]
    if logs.shape[1] == 0:
        return offsets
    for _ in range(iterations):
        radiance = np.nanmedian(logs - offsets[:, None], axis=0)
        residual = logs - radiance[None, :]
        seen = np.isfinite(residual).any(1)
        offsets[seen] = np.nanmedian(residual[seen], axis=1)
        offsets -= offsets[reference]
    return offsets


def build_view_exposures(config: ExposureConfig, scene) -> ViewExposures | None:
    """The per-view exposure model of a training run on `scene` (SceneData), or None when every
    training view has the same known exposure and nothing is learned (the paper's setting)."""
    unknown = set(scene.metadata.get("unknown_exposures", ()))
    learn = config.learn_exposure if config.learn_exposure is not None else bool(unknown)
    exposures = [view.exposure for view in scene.train]
    balance = learns_white_balance(config, scene, learn)
    if not learn and not balance and len({round(math.log(e), 6) for e in exposures}) == 1:
        return None
    reference = reference_view(scene.train)
    response = scene.metadata.get("camera_response")
    response = np.asarray(response) if response is not None else srgb_response()
    initial = np.array([math.log(e / exposures[reference]) for e in exposures])
    missing = [i for i, view in enumerate(scene.train) if view.name in unknown]
    if missing and scene.points is not None:
        measured = photometric_log_exposures(scene.train, scene.points, response, reference)
        initial[missing] = measured[missing]
    return ViewExposures(
        torch.from_numpy(initial),
        reference,
        exposures[reference],
        response,
        learn=learn,
        learning_rate=config.exposure_lr,
        names=[view.name for view in scene.train],
        known=not unknown,
        white_balance=ViewWhiteBalance(
            len(scene.train), config.white_balance_lr, config.white_balance_pull, [view.name for view in scene.train]
        )
        if balance
        else None,
    )


def learns_white_balance(config: ExposureConfig, scene, learn_exposure: bool) -> bool:
    """--learn-white-balance: auto learns the gains where the exposures are learned (a capture that
    knows neither) or where the photos' EXIF says the camera chose the white balance itself
    (metadata["auto_white_balance"], written by process-data)."""
    if config.learn_white_balance != "auto":
        return config.learn_white_balance == "on"
    return learn_exposure or bool(scene.metadata.get("auto_white_balance"))
