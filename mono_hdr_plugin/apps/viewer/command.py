"""`mono-hdr view`: a trained model in the browser."""

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from rich.console import Console

from mono_hdr_plugin.apps.viewer.gui import Viewer, wait_for_interrupt
from mono_hdr_plugin.apps.viewer.renderer import ViewerRenderer
from mono_hdr_plugin.apps.viewer.snapshots import ModelSnapshots
from mono_hdr_plugin.core.validation import at_least, between
from mono_hdr_plugin.training.trained import load_trained_model

console = Console(stderr=True)


@dataclass
class ViewConfig:
    """Look at a trained model in the browser: exposure, tone mapping, depth, errors, dataset cameras."""

    checkpoint: Path
    """A checkpoint written by `mono-hdr train`."""
    port: int = 7007
    """Port to listen on (the next free one when taken; 0: any free port)."""
    host: str = "127.0.0.1"
    """Address to listen on. The default admits this machine only; 0.0.0.0 opens the viewer to
    the network, with no authentication (anyone who reaches it sees the model and can save views)."""
    out: Path = Path("outputs/viewer")
    """Folder for views saved with the viewer's Save button."""
    max_resolution: int = 512
    """Longest side of a still frame in pixels (a slider in the viewer)."""

    flag_rules: ClassVar = {"port": between(0, 65535), "max_resolution": at_least(1)}


def view_command(config: ViewConfig) -> None:
    model = load_trained_model(config.checkpoint)
    snapshots = ModelSnapshots(model.pipeline, model.step, copy_model=False)
    viewer = Viewer(
        ViewerRenderer(snapshots, model.scene),
        host=config.host,
        port=config.port,
        out=config.out,
        max_resolution=config.max_resolution,
    )
    console.print(f"[bold]viewer of {config.checkpoint} (step {model.step}) at {viewer.url}[/bold]  (Ctrl+C to stop)")
    try:
        wait_for_interrupt()
    finally:
        viewer.stop()
    console.print("viewer stopped")
