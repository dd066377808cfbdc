"""The models a viewer renders, shared between the thread that owns the model and the render threads.

viser runs its own event loop and calls the GUI callbacks from a thread pool; each connected
browser gets one render thread. During training the model lives in the training thread, which
must never wait for rendering, so the two share it through `ModelSnapshots`: the training
thread, between two steps, deep-copies the pipeline (a few MB, at most every
`SnapshotPublisher.min_interval` seconds and only while a browser is connected) and swaps the
copy in under a lock that guards nothing but that one reference. A published snapshot is never
modified again, so render threads use it without any lock while training goes on with the live
model.
"""

import copy
import threading
from dataclasses import dataclass

from mono_hdr_plugin.training.pipeline import Pipeline


@dataclass(frozen=True)
class Snapshot:
    """A model the viewer may render; never modified after it was published."""

    pipeline: Pipeline
    step: int
    version: int


class ModelSnapshots:
    """The latest published model, shared by the thread that owns it and the render threads."""

    def __init__(self, pipeline: Pipeline, step: int, copy_model: bool = True):
        self._lock = threading.Lock()
        self._latest: Snapshot | None = None
        self.publish(pipeline, step, copy_model)

    def publish(self, pipeline: Pipeline, step: int, copy_model: bool = True) -> None:
        """Make (a frozen copy of) this model the one rendered from now on. With copy_model the
        caller may keep changing its own model: call it from the thread that changes it."""
        if copy_model:
            pipeline = copy.deepcopy(pipeline)
            pipeline.eval()
            pipeline.requires_grad_(False)
        with self._lock:
            version = 0 if self._latest is None else self._latest.version + 1
            self._latest = Snapshot(pipeline, step, version)

    def latest(self) -> Snapshot:
        with self._lock:
            assert self._latest is not None  # __init__ publishes the first model
            return self._latest
