"""Exposure protocols: which photo of each view a run trains and tests on.

single (Mono-HDR-3D): one exposure t1, t3 or t5 (--exposure-index 0, 1, 2) for every train AND
    test view, as the official `exps_index` does.
multi (HDR-NeRF / HDR-GS): each train view one random exposure of t1/t3/t5 (seeded); every
    test view at all its exposures.
fixed: every view at --fixed-exposure seconds.

Views photographed once (a user's own photos, any exposure) are used as they are under
single and multi: there is nothing to choose from.
"""

import numpy as np

from mono_hdr_plugin.data.captures import CapturedScene, CapturedView, Shot
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.errors import DatasetError


def training_levels(levels: list[float]) -> list[float]:
    """t1, t3, t5 of five exposure levels (all of them when there are three)."""
    if len(levels) == 5:
        return [levels[0], levels[2], levels[4]]
    if len(levels) == 3:
        return list(levels)
    raise DatasetError(
        f"the data has {len(levels)} exposure level(s) {levels}; the single and multi "
        "protocols need 3 or 5 (t1..t5): use --protocol fixed --fixed-exposure SECONDS"
    )


def _shot_at(view: CapturedView, exposure: float, argument: str) -> Shot:
    for shot in view.shots:
        if np.isclose(shot.exposure, exposure, rtol=1e-3, atol=0):
            return shot
    have = [shot.exposure for shot in view.shots]
    raise DatasetError(
        f"view {view.name or view.view_id} has no photo at {exposure} s (it has {have}); choose another {argument}"
    )


def _single(scene: CapturedScene, config: DataConfig):
    if config.exposure_index not in (0, 1, 2):
        raise DatasetError(f"--exposure-index must be 0, 1 or 2 (t1, t3, t5), got {config.exposure_index}")
    exposure = training_levels(scene.exposure_levels)[config.exposure_index]
    return {id(view): [_shot_at(view, exposure, "--exposure-index")] for view in scene.views}


def _multi(scene: CapturedScene, config: DataConfig):
    allowed = training_levels(scene.exposure_levels)
    rng = np.random.default_rng(config.exposure_seed)
    chosen = {}
    for view in scene.views:
        if view.split == "test":
            chosen[id(view)] = list(view.shots)
            continue
        candidates = [shot for shot in view.shots if np.isclose(shot.exposure, allowed, rtol=1e-3, atol=0).any()]
        if not candidates:
            raise DatasetError(f"view {view.name or view.view_id} has no photo at t1/t3/t5 {allowed}")
        chosen[id(view)] = [candidates[rng.integers(len(candidates))]]
    return chosen


def _fixed(scene: CapturedScene, config: DataConfig):
    if config.fixed_exposure is None or not config.fixed_exposure > 0:
        raise DatasetError(
            "--protocol fixed needs --fixed-exposure SECONDS (a positive exposure "
            f"the data has: {scene.exposure_levels})"
        )
    return {id(view): [_shot_at(view, config.fixed_exposure, "--fixed-exposure")] for view in scene.views}


PROTOCOLS = {"single": _single, "multi": _multi, "fixed": _fixed}


def select_shots(scene: CapturedScene, config: DataConfig) -> dict[int, list[Shot]]:
    """The photos each view contributes, keyed by id(view), under config.protocol."""
    if config.protocol not in PROTOCOLS:
        raise DatasetError(f"unknown --protocol {config.protocol!r}; choose from {sorted(PROTOCOLS)}")
    if config.protocol != "fixed" and all(len(view.shots) == 1 for view in scene.views):
        return {id(view): list(view.shots) for view in scene.views}
    return PROTOCOLS[config.protocol](scene, config)
