"""Register a new dataset layout from outside the package: one JSON file that says everything.

    <scene>/scene.json       {"format": "scene-json 1", "bounds": [[x, y, z], [x, y, z]],
                              "views": [{"split": "train", "c2w": 4x4 (OpenCV), "fx": .., "fy": .., "cx": ..,
                                         "cy": .., "width": .., "height": .., "near": .., "far": ..,
                                         "photos": [{"file": "photos/000_0.png", "exposure": 0.125}, ...],
                                         "hdr": "hdr/000.exr" or null}, ...]}
    <scene>/photos/*.png     <scene>/hdr/*.exr

One class and one decorator: `mono-hdr train gs --data <scene>` then detects and reads it, and
`mono-hdr synth --layout scene-json` writes a studio scene in it (when this module is imported,
or declared in your package's `mono_hdr.layouts` entry-point group).

    python examples/register_layout.py --scene demo --out outputs/scene-json
"""

import argparse
import functools
import json
from pathlib import Path

import torch

from mono_hdr_plugin.data.captures import CapturedScene, CapturedView, Shot
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.io import read_exr, read_image, write_exr, write_json, write_png
from mono_hdr_plugin.data.layouts import DatasetLayout, register_layout
from mono_hdr_plugin.data.layouts.common import camera_from, check_exposure

FORMAT = "scene-json 1"
CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "near", "far")


@register_layout("scene-json")
class SceneJsonLayout(DatasetLayout):
    description = "scene.json (cameras, exposures, file names) + photos/ + hdr/"
    writable = True

    @staticmethod
    def detect(folder: Path) -> bool:
        return (folder / "scene.json").is_file()

    @staticmethod
    def read(folder: Path) -> CapturedScene:
        index_file = folder / "scene.json"
        try:
            index = json.loads(index_file.read_text())
            if index.get("format") != FORMAT:
                raise DatasetError(f"{index_file}: format {index.get('format')!r}, expected {FORMAT!r}")
            views = []
            for number, entry in enumerate(index["views"]):
                where = f"{index_file} view {number}"
                camera = camera_from(
                    where,
                    c2w=torch.tensor(entry["c2w"], dtype=torch.float32),
                    **{key: entry[key] for key in CAMERA_KEYS},
                )
                shots = [
                    Shot(
                        check_exposure(photo["exposure"], where),
                        functools.partial(read_image, folder / photo["file"]),
                        photo["file"],
                    )
                    for photo in entry["photos"]
                ]
                hdr = functools.partial(read_exr, folder / entry["hdr"]) if entry.get("hdr") else None
                views.append(
                    CapturedView(
                        view_id=number,
                        camera=camera,
                        split=entry["split"],
                        name=f"{number:03d}",
                        shots=sorted(shots, key=lambda shot: shot.exposure),
                        hdr=hdr,
                    )
                )
            low, high = (torch.tensor(corner, dtype=torch.float32) for corner in index["bounds"])
        except (KeyError, TypeError, ValueError) as error:
            if isinstance(error, DatasetError):
                raise
            raise DatasetError(
                f"{index_file}: {type(error).__name__}: {error}; see the format in examples/register_layout.py"
            ) from error
        return CapturedScene(
            name=folder.name,
            views=views,
            bounds_min=low,
            bounds_max=high,
            metadata={"source": str(folder), "layout": "scene-json"},
        )

    @staticmethod
    def write(scene: CapturedScene, folder: Path, bits: int = 8) -> None:
        views = []
        for view in scene.views:
            camera = view.camera
            photos = []
            for level, shot in enumerate(view.shots):
                name = f"photos/{view.view_id:03d}_{level}.png"
                write_png(folder / name, shot.image(), bits=bits)
                photos.append({"file": name, "exposure": shot.exposure})
            hdr = None
            if view.hdr is not None:
                hdr = f"hdr/{view.view_id:03d}.exr"
                write_exr(folder / hdr, view.hdr())
            views.append(
                {
                    "split": view.split,
                    "c2w": camera.c2w.tolist(),
                    "photos": photos,
                    "hdr": hdr,
                    **{key: getattr(camera, key) for key in CAMERA_KEYS},
                }
            )
        write_json(
            folder / "scene.json",
            {"format": FORMAT, "views": views, "bounds": [scene.bounds_min.tolist(), scene.bounds_max.tolist()]},
        )


def main() -> None:
    from mono_hdr_plugin.data.layouts import write_layout
    from mono_hdr_plugin.data.sources import named_scene

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--out", type=Path, default=Path("outputs/scene-json"))
    args = parser.parse_args()
    write_layout(named_scene(args.scene), args.out, "scene-json")
    print(f"wrote {args.scene} to {args.out} in the scene-json layout")


if __name__ == "__main__":
    main()
