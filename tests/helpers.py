"""Test helpers shared by several test folders (imported as `from helpers import ...`)."""

from contextlib import contextmanager
from dataclasses import replace


class FakeClock:
    """perf_counter that advances a fixed amount per call: a step of the trainer reads it twice."""

    def __init__(self, seconds_per_call: float):
        self.now, self.seconds_per_call = 0.0, seconds_per_call

    def perf_counter(self) -> float:
        self.now += self.seconds_per_call
        return self.now


def quiet_config(backbone_config, out, method: str | None = None, **settings):
    """The run config of `method` (None: the default) on `backbone_config`, training into `out` without
    output on the terminal, renders or checkpoints before the end; `settings` are further TrainConfig
    fields and override these."""
    from mono_hdr_plugin.training.config import train_config_for

    quiet = {"quiet": True, "save_renders": False, "checkpoint_every": 10**9}
    return train_config_for(type(backbone_config), method)(backbone=backbone_config, out=out, **(quiet | settings))


def real_photos(name: str):
    """The folder of a real capture beside the project (`shared/data/real/<name>`: third-party photos
    read in place, never copied into the repository). Skipped where it is absent, except under CI,
    which always has it: there a missing folder fails instead of passing silently."""
    import os
    from pathlib import Path

    import pytest

    folder = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real" / name
    if not folder.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"{folder}: the real photos are missing; CI runs beside shared/data/real")
        pytest.skip(f"{folder}: real photos not available here")
    return folder


def tiny_variant(scene):
    """A built-in scene at 24x24, 4 samples per pixel, 10 views: renders in about a second."""
    return replace(scene, resolution=(24, 24), spp=4, rig=replace(scene.rig, views=10))


@contextmanager
def tiny_builtin_scenes():
    """While it lasts, `--scene NAME` finds the tiny variant of each built-in scene. The default suite's
    tests have it by an autouse fixture; a session or module fixture, set up before that one, enters it
    itself (with the `studio_cache` fixture, so the renders go to the session's cache)."""
    import pytest

    from mono_hdr_plugin.apps.studio.scenes import BUILTIN_SCENES, SCENES

    with pytest.MonkeyPatch.context() as patch:
        for scene in BUILTIN_SCENES:
            patch.setitem(SCENES, scene.name, tiny_variant(scene))
        yield
