"""README figures: one studio view at three exposures and its HDR tone-mapped.

    python -m mono_hdr_plugin.apps.studio.figures [scene] [out_folder]

writes docs/studio_<scene>_t1.png, _t3.png, _t5.png and _hdr.png.
"""

import sys
from pathlib import Path

import numpy as np
import torch

from mono_hdr_plugin.apps.studio.capture import capture
from mono_hdr_plugin.apps.studio.dataset import get_scene
from mono_hdr_plugin.apps.studio.render import render_scene
from mono_hdr_plugin.core.metrics import normalise_hdr
from mono_hdr_plugin.data.io import write_png


def upscale(image: np.ndarray, factor: int) -> np.ndarray:
    """Nearest-neighbour enlargement, so small renders stay crisp in the README."""
    return image.repeat(factor, axis=0).repeat(factor, axis=1)


def write_figures(scene_name: str = "demo", out: Path = Path("docs"), view: int = 0, factor: int = 4) -> list[Path]:
    """Write the figures and return their paths."""
    scene = get_scene(scene_name)
    radiance = render_scene(scene).radiance[view]
    paths = []
    for label, index in (("t1", 0), ("t3", 2), ("t5", 4)):
        photo = capture(radiance, scene.exposures[index], scene.effects, scene.capture)
        paths.append(out / f"studio_{scene_name}_{label}.png")
        write_png(paths[-1], upscale(photo, factor))
    paths.append(out / f"studio_{scene_name}_hdr.png")
    write_png(
        paths[-1], upscale(normalise_hdr(torch.from_numpy(radiance)).numpy(), factor)
    )  # as the HDR metric sees it
    return paths


if __name__ == "__main__":
    arguments = sys.argv[1:]
    scene_name = arguments[0] if arguments else "demo"
    paths = write_figures(scene_name, Path(arguments[1])) if len(arguments) > 1 else write_figures(scene_name)
    for path in paths:
        print(path)
