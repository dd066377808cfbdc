"""`mono-hdr train ... --viewer`: a viewer on the model while it trains; training never waits for it."""

import math
import time
from collections.abc import Callable

from rich.console import Console

from mono_hdr_plugin.apps.viewer.gui import Viewer, wait_for_interrupt
from mono_hdr_plugin.apps.viewer.renderer import ViewerRenderer
from mono_hdr_plugin.apps.viewer.snapshots import ModelSnapshots
from mono_hdr_plugin.training.hooks import TrainingHook

console = Console(stderr=True)


class SnapshotPublisher(TrainingHook):
    """A training hook: publishes a copy of the model while someone watches.

    Copies are spaced so that copying takes at most 1/20 of the training time (and at least
    `min_interval` seconds apart): the viewer may lag, training barely notices.
    """

    def __init__(
        self,
        snapshots: ModelSnapshots,
        watched: Callable[[], bool],
        on_publish: Callable[[int], None],
        min_interval: float = 1.0,
    ):
        self.snapshots, self.watched, self.on_publish = snapshots, watched, on_publish
        self.min_interval = min_interval
        self.interval = min_interval
        self.published_at = -math.inf
        self.published_step = -1

    def after_step(self, trainer, record: dict) -> None:
        if time.perf_counter() - self.published_at >= self.interval:
            self._publish(trainer)

    def on_end(self, trainer) -> None:
        # The finished model is always shown, however the copies were spaced.
        if self.published_step != trainer.step:
            self._publish(trainer)

    def _publish(self, trainer) -> None:
        if not self.watched():
            return
        now = time.perf_counter()
        self.snapshots.publish(trainer.pipeline, trainer.step)
        copy_seconds = time.perf_counter() - now
        self.interval = max(self.min_interval, 20.0 * copy_seconds)
        self.published_at = time.perf_counter()
        self.published_step = trainer.step
        self.on_publish(trainer.step)


def train_with_viewer(trainer, report: Callable[[dict], None]) -> dict:
    """Train while a viewer shows the model (training never waits for it); after training the
    viewer stays open on the final model until Ctrl+C. `report` receives the metrics first."""
    config = trainer.config
    snapshots = ModelSnapshots(trainer.pipeline, trainer.step)
    viewer = Viewer(
        ViewerRenderer(snapshots, trainer.scene),
        host=config.viewer_host,
        port=config.viewer_port,
        out=config.out / "viewer",
        training=True,
    )
    console.print(f"[bold]viewer at {viewer.url}[/bold]")
    try:
        metrics = trainer.train(extra_hooks=[SnapshotPublisher(snapshots, viewer.has_clients, viewer.training_step)])
        snapshots.publish(trainer.pipeline, trainer.step)
        viewer.training_step(trainer.step)
        report(metrics)
        console.print(f"[bold]training done; the viewer stays at {viewer.url}[/bold]  (Ctrl+C to stop)")
        wait_for_interrupt()
    finally:
        viewer.stop()
    return metrics
