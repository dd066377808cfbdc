"""Make the README's viewer screenshot and exposure-sweep strip from a trained checkpoint.

    python examples/viewing_figures.py --checkpoint outputs/demo/checkpoints/latest.pt --out docs

Starts the viewer on a free local port with the given output and exposure, photographs the
page in headless Chromium (Debian's chromium + chromium-driver), and renders the sweep
EV -6 to +6 at the second test camera.
"""

import argparse
from pathlib import Path

import numpy as np
from browser_screenshot import screenshot_when

from mono_hdr_plugin.apps.render import render_exposure_sweep
from mono_hdr_plugin.apps.viewer.gui import Viewer
from mono_hdr_plugin.apps.viewer.renderer import VIEWER_OUTPUTS, ViewerRenderer
from mono_hdr_plugin.apps.viewer.snapshots import ModelSnapshots
from mono_hdr_plugin.training.evaluation import first_per_camera
from mono_hdr_plugin.training.trained import load_trained_model

# Viser's warning that WebGL runs in software (true in a headless browser) covers the render.
CLOSE_NOTIFICATIONS = "document.querySelectorAll('.mantine-Notification-root').forEach(n => n.remove())"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=Path("docs"))
    parser.add_argument("--output", default="hdr-filmic", choices=list(VIEWER_OUTPUTS))
    parser.add_argument("--ev", type=float, default=1.0)
    parser.add_argument("--view", type=int, default=1, help="test camera of the sweep and the screenshot")
    args = parser.parse_args()
    model = load_trained_model(args.checkpoint)
    camera = first_per_camera(model.scene.test)[args.view].camera
    strip_camera = camera.scaled(2.0)  # the dataset's 64 px are small on a page

    evs = np.linspace(-6, 6, 7).tolist()
    render_exposure_sweep(model, strip_camera, evs, args.out / "exposure_sweep.mp4", args.out / "exposure_sweep.png")
    (args.out / "exposure_sweep.mp4").unlink()

    snapshots = ModelSnapshots(model.pipeline, model.step, copy_model=False)
    viewer = Viewer(ViewerRenderer(snapshots, model.scene), port=0, out=args.out / "saved_views")
    try:
        viewer.output.value = VIEWER_OUTPUTS[args.output]
        viewer.ev.value = args.ev
        name = next(key for key, view in viewer.renderer.views.items() if view.camera is camera)
        viewer.view_choice.value = name
        viewer.server.initial_camera.position = tuple(float(v) for v in camera.center)
        screenshot_when(
            viewer.url,
            args.out / "viewer.png",
            lambda pixels: pixels[100:-60, 60:800].std() > 8,
            script=CLOSE_NOTIFICATIONS,
        )
    finally:
        viewer.stop()
    print(f"wrote {args.out / 'viewer.png'} and {args.out / 'exposure_sweep.png'}")


if __name__ == "__main__":
    main()
