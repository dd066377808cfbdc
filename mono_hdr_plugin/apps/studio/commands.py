"""`mono-hdr synth` and `mono-hdr scenes`: configs and functions the CLI wires in."""

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from mono_hdr_plugin.apps.studio.render import (
    about_minutes,
    cache_dir,
    dynamic_range,
    render_cache_path,
    render_minutes,
    render_scene,
)
from mono_hdr_plugin.apps.studio.scene import StudioScene
from mono_hdr_plugin.apps.studio.scenes import SCENES
from mono_hdr_plugin.core.validation import MAX_IMAGE_SIDE, SEED, FlagError, between


@dataclass
class SynthConfig:
    """Write a built-in studio scene to disk in a published dataset layout."""

    scene: str = "demo"
    """Built-in scene to write (see `mono-hdr scenes`)."""
    out: Path = Path("outputs/synth")
    """Folder to write the dataset into (created if missing)."""
    layout: str = "hdr-gs"
    """A writable layout (`mono-hdr layouts`): hdr-gs (images/, exr/, COLMAP sparse/0, exposures.json),
    hdr-nerf-synthetic (transforms/exposure JSON, PNGs, EXR), hdr-nerf-real, or llff / nerfstudio
    (one photo a view, the middle exposure, no exposure times and no HDR: as real captures come)."""
    seed: int = 0
    """Seed of the simulated sensor noise."""
    resolution: int | None = None
    """Render and photograph at N x N pixels (default: the scene's own 128; each size is rendered once and
    cached; the cameras keep their field of view)."""
    overwrite: bool = False
    """Replace a dataset an earlier `mono-hdr synth` wrote in --out instead of refusing."""

    flag_rules: ClassVar = {"seed": SEED, "resolution": between(8, MAX_IMAGE_SIDE)}


@dataclass
class ScenesConfig:
    """List the built-in studio scenes with their dynamic range and render noise (rendered first where not cached)."""

    render: bool = True
    """Measure the dynamic range and the seed agreement from the renders (cached; a scene not yet
    rendered takes about 2 minutes on 2 cores at 128 px, once, and time grows with the pixels);
    --no-render lists at once without them."""
    resolution: int | None = None
    """List (and render) the scenes at N x N pixels (default: their own 128)."""

    flag_rules: ClassVar = {"resolution": between(8, MAX_IMAGE_SIDE)}


def png_bits(scene: StudioScene) -> int:
    """8-bit PNGs hold an 8-bit capture exactly; deeper captures (or none) need 16 bits."""
    return 8 if "quantize" in scene.effects and scene.capture.bits == 8 else 16


def synth(config: SynthConfig) -> Path:
    """Render (or reuse the cached render of) a scene and write every photo at t1..t5."""
    from mono_hdr_plugin.apps.studio.dataset import get_scene, studio_captured_scene
    from mono_hdr_plugin.data.layouts import writable_layouts, write_layout
    from mono_hdr_plugin.data.outputs import claim_output

    if config.layout not in writable_layouts():  # before minutes of rendering, not after
        raise FlagError(f"--layout {config.layout!r} cannot be written; choose one of {', '.join(writable_layouts())}")
    get_scene(config.scene)
    # The whole folder is the dataset: an earlier one of another layout left beside it would be detected first.
    with claim_output(config.out, "synth", None, overwrite=config.overwrite) as output:
        scene = get_scene(config.scene, config.resolution)
        captured = studio_captured_scene(scene, seed=config.seed)
        output.clear_previous()
        write_layout(captured, config.out, config.layout, bits=png_bits(scene))
    return config.out


def scenes_at(resolution: int | None) -> list[StudioScene]:
    """Every built-in scene, at `resolution` x `resolution` pixels if given."""
    from mono_hdr_plugin.apps.studio.dataset import get_scene

    return [get_scene(name, resolution) for name in SCENES]


def list_scenes(render: bool = True, resolution: int | None = None) -> list[dict]:
    """One row per scene: name, resolution, views, spp, effects and, when rendered, the dynamic
    range and how well two renders with different seeds agree (worst view, dB; None unless rendered)."""
    rows = []
    for scene in scenes_at(resolution):
        row = {
            "name": scene.name,
            "resolution": f"{scene.width}x{scene.height}",
            "views": scene.rig.views,
            "spp": scene.spp,
            "description": scene.description,
            "effects": scene.effects,
            "dynamic_range": None,
            "agreement_hdr": None,
            "agreement_ldr": None,
        }
        if render:
            rendered = render_scene(scene)
            row.update(
                dynamic_range=dynamic_range(rendered.radiance),
                agreement_hdr=float(rendered.agreement_hdr.min()),
                agreement_ldr=float(rendered.agreement_ldr.min()),
            )
        rows.append(row)
    return rows


def list_scenes_command(config: ScenesConfig) -> None:
    """Print the built-in scenes as a table."""
    from rich.console import Console
    from rich.table import Table

    table = Table(
        title="Built-in studio scenes",
        caption="seed agreement: PSNR between two renders of each view with different seeds (worst "
        "view), mu-law HDR and the noise-free photo at t3; the ground truth is their mean",
    )
    for column in (
        "name",
        "resolution",
        "views",
        "spp",
        "dynamic range",
        "seed agreement HDR / LDR",
        "capture effects",
        "description",
    ):
        table.add_column(column)
    missing = [scene for scene in scenes_at(config.resolution) if not render_cache_path(scene).is_file()]
    if config.render and missing:
        estimates = {scene.name: render_minutes(scene) for scene in missing}
        minutes = sum(minutes for minutes, _ in estimates.values())
        guessed = [name for name, (_, measured) in estimates.items() if not measured]
        Console(stderr=True, soft_wrap=True).print(
            f"{len(missing)} of {len(SCENES)} built-in scenes are not rendered yet at this size "
            f"({', '.join(scene.name for scene in missing)}): rendering them first, {about_minutes(minutes)}"
            + (f" (at demo's rate for {', '.join(guessed)}, never rendered here)" if guessed else "")
            + ", once (cached in "
            f"{cache_dir() / 'studio'}); `mono-hdr scenes --no-render` lists them now without the measured columns",
            markup=False,
            highlight=False,
        )
    for row in list_scenes(config.render, config.resolution):
        if row["dynamic_range"] is None:
            ratio = agreement = "not rendered"
        else:
            ratio = f"{row['dynamic_range']:.2g} : 1"
            agreement = f"{row['agreement_hdr']:.1f} / {row['agreement_ldr']:.1f} dB"
        table.add_row(
            row["name"],
            row["resolution"],
            str(row["views"]),
            f"2 x {row['spp']}",
            ratio,
            agreement,
            ", ".join(row["effects"]),
            row["description"],
        )
    Console().print(table)
