"""How fast the viewer renders a checkpoint: seconds per frame and pixels per second at the
viewer's still and moving sizes, and the size it picks while the camera moves.

    python benchmarks/viewer_speed.py --checkpoint outputs/demo/checkpoints/latest.pt \\
        --out benchmarks/results/viewer_speed.json

Run on a quiet machine: the figures are wall-clock seconds of one render thread.
"""

import json
import math
import platform
import statistics
import subprocess
import time
from pathlib import Path

import torch

from mono_hdr_plugin.apps.bench import script_args as args_of
from mono_hdr_plugin.apps.camera_paths import viewer_from_camera
from mono_hdr_plugin.apps.viewer.gui import MIN_HEIGHT, MOVING_FRAME_SECONDS
from mono_hdr_plugin.apps.viewer.renderer import ViewerRenderer
from mono_hdr_plugin.apps.viewer.snapshots import ModelSnapshots
from mono_hdr_plugin.training.evaluation import first_per_camera
from mono_hdr_plugin.training.trained import load_trained_model


def main() -> None:
    parser = args_of.script_parser(__doc__)
    parser.add_argument("--checkpoint", type=Path, required=True)
    args_of.add_out(parser, None)
    parser.add_argument("--heights", type=args_of.COUNT, nargs="+", default=[64, 128, 256, 384])
    args_of.add_count(parser, "--repeats", 5, "timed renders per height (median)")
    args = parser.parse_args()
    model = load_trained_model(args.checkpoint)
    renderer = ViewerRenderer(ModelSnapshots(model.pipeline, model.step, copy_model=False), model.scene)
    camera = viewer_from_camera(first_per_camera(model.scene.test)[0].camera)
    aspect_camera = type(camera)(camera.wxyz, camera.position, camera.fov, 4 / 3)  # a 4:3 browser canvas
    rows = []
    for height in args.heights:
        renderer.render(aspect_camera, height, "hdr-filmic", 0.0)  # warm-up
        seconds = []
        for _ in range(args.repeats):
            started = time.perf_counter()
            renderer.render(aspect_camera, height, "hdr-filmic", 0.0)
            seconds.append(time.perf_counter() - started)
        median = statistics.median(seconds)
        pixels = height * round(height * 4 / 3)
        rows.append(
            {
                "height": height,
                "width": round(height * 4 / 3),
                "median_seconds": median,
                "pixels_per_second": pixels / median,
                "fps": 1.0 / median,
            }
        )
        print(f"{rows[-1]['width']} x {height}: {median * 1000:.0f} ms ({1 / median:.1f} fps)")
    rate = statistics.median(row["pixels_per_second"] for row in rows)
    moving_height = max(MIN_HEIGHT, int(math.sqrt(rate * MOVING_FRAME_SECONDS / (4 / 3))))
    result = {
        "checkpoint": str(args.checkpoint),
        "backbone": model.pipeline.backbone_name,
        "method": model.pipeline.method_name,
        "torch_threads": torch.get_num_threads(),
        "machine": platform.processor() or platform.machine(),
        "commit": subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip(),
        "renders": rows,
        "moving_height": moving_height,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"while moving the viewer renders about {round(moving_height * 4 / 3)} x {moving_height}; wrote {args.out}")


if __name__ == "__main__":
    main()
