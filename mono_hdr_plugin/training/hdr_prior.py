"""HDR from the photos themselves, where no HDR view exists (docs/method.md, "HDR without HDR views").

The paper's HDR branch learns radiance from HDR ground-truth views; without them nothing ties it to
radiance, and it comes out as any function of the LDR colour that H2L-CC can invert (a channel can
even come out inverted). What the photos do say: where a photo is well exposed, the radiance it
records is f^-1(photo) / t, f the camera response and t the exposure, up to one global scale. L_prior
(methods.base) holds the HDR render to that, with t relative to the reference view so the level
starts near the converter's; where the photo clips, L2H-CC (non-decreasing) extrapolates.

`hdr_basis` names what the HDR of a run rests on; the calibration carries it into metrics.json, the
training log, `eval` and the export.
"""

import math

import numpy as np
import torch
from torch import Tensor

from mono_hdr_plugin.core.exposure import ViewExposures, decode, srgb_response
from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.methods.base import HDR_PRIOR_WEIGHT, MethodConfig


def ground_truth_views(scene: SceneData, hdr_views: list[bool] | None) -> list[bool]:
    """Per training view: whether training reads its HDR ground truth (it has one, and `hdr_views`,
    the --hdr-view-ratio selection, picks it; None picks every view)."""
    picked = hdr_views if hdr_views is not None else [True] * len(scene.train)
    return [use and view.hdr is not None for use, view in zip(picked, scene.train, strict=True)]


def resolve_prior_weight(config: MethodConfig, uses_ground_truth: bool) -> float:
    """--hdr-prior-weight, or its default: HDR_PRIOR_WEIGHT when no training view has HDR ground truth."""
    if config.hdr_prior_weight is not None:
        return config.hdr_prior_weight
    return 0.0 if uses_ground_truth else HDR_PRIOR_WEIGHT


def camera_response(scene: SceneData, exposures: ViewExposures | None) -> Tensor:
    """The response table [256, 3] training uses: the per-view exposure model's, else the capture's
    (process-data's camera_response.json, the studio's capture curve), else sRGB."""
    if exposures is not None:
        return exposures.response
    response = scene.metadata.get("camera_response")
    return torch.as_tensor(np.asarray(response) if response is not None else srgb_response(), dtype=torch.float32)


def response_name(scene: SceneData) -> str:
    """What the response of `camera_response` is, in words."""
    if scene.metadata.get("camera_response") is None:
        return "the sRGB response (assumed: the capture gives none)"
    return f"the camera response {scene.metadata.get('camera_response_source', 'of the capture')}"


def prior_radiance(photo: Tensor, response: Tensor, relative_exposure: float | Tensor) -> Tensor:
    """f^-1(photo) / (t / t_ref): the radiance a photo [..., 3] records, at the reference view's exposure
    (`relative_exposure` [3] where white balance is learned: its gains divided out too)."""
    return decode(photo, response) / relative_exposure


def hdr_basis(scene: SceneData, hdr_views: list[bool] | None, exposures: ViewExposures | None) -> str:
    """What ties a run's HDR to radiance: the HDR ground-truth views it trains on, else the camera
    response (and the exposure ratios across views, where they vary or are learned, and the white
    balance, where it is learned)."""
    count = sum(ground_truth_views(scene, hdr_views))
    if count:
        return f"{count} HDR ground-truth view{'s' if count != 1 else ''}"
    basis = f"{response_name(scene)}, no HDR views"
    times = [view.exposure for view in scene.train]
    if exposures is not None and exposures.learned:
        known = "EXIF times as a start" if exposures.known else "the capture knows no times"
        basis += f"; exposure ratios across views, learned ({known})"
    elif len({round(math.log(t), 6) for t in times}) > 1:
        basis += f"; exposure ratios across views ({min(times):g}-{max(times):g} s)"
    if exposures is not None and exposures.white_balance is not None:
        basis += "; white balance per view, learned (the HDR keeps the photos' mean balance)"
    return basis
