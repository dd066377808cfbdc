"""Evaluation of large views holds one view's intermediates at a time: peak memory does not grow with views."""

import weakref

import torch
from known_render import KnownRenderConfig, camera_at, ground_truth
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

import mono_hdr_plugin.training.evaluation as evaluation
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.trainer import Trainer

SIDE = 512
IMAGE_BYTES = SIDE * SIDE * 3 * 4


class LiveTensorBytes(TorchDispatchMode):
    """Bytes of the CPU tensor storages that torch ops made inside the mode and that are still alive; its peak."""

    def __init__(self):
        super().__init__()
        self.live: dict[int, list[int]] = {}  # storage address -> [bytes, live tensors on it]
        self.now = self.peak = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for tensor in tree_leaves(out):
            if isinstance(tensor, torch.Tensor) and tensor.device.type == "cpu":
                self._track(tensor)
        return out

    def _track(self, tensor: torch.Tensor) -> None:
        storage = tensor.untyped_storage()
        address = storage.data_ptr()
        if address == 0:
            return
        if address not in self.live:
            self.live[address] = [storage.nbytes(), 0]
            self.now += storage.nbytes()
            self.peak = max(self.peak, self.now)
        self.live[address][1] += 1
        weakref.finalize(tensor, self._release, address)

    def _release(self, address: int) -> None:
        entry = self.live[address]
        entry[1] -= 1
        if entry[1] == 0:
            self.now -= entry[0]
            del self.live[address]


def large_view(x: float, view_id: int) -> View:
    camera = camera_at(x).scaled(SIDE / camera_at(x).width)
    ldr, hdr = ground_truth(camera, view_id)
    return View(camera=camera, image=ldr, exposure=0.5, view_id=view_id, name=f"cam{view_id}", hdr=hdr)


def peak_of_evaluation(tmp_path, views: int) -> int:
    train = [large_view(-1.0, 100), large_view(1.0, 101)]
    test = [large_view(0.2 * index, index) for index in range(views)]
    scene = SceneData("large", train, test, torch.full((3,), -4.0), torch.full((3,), 4.0))
    config = train_config_for(KnownRenderConfig)(backbone=KnownRenderConfig(), out=tmp_path, quiet=True, max_steps=1)
    pipeline = Trainer(config, "known-render", scene).pipeline
    with LiveTensorBytes() as memory:
        metrics = evaluation.evaluate(pipeline, scene)
    assert metrics["test_views"] == views and metrics["hdr_psnr"] is not None
    return memory.peak


def test_peak_does_not_grow_with_the_number_of_views(tmp_path, monkeypatch):
    monkeypatch.setattr(evaluation, "load_lpips", lambda: (_ for _ in ()).throw(evaluation.LpipsUnavailable("off")))
    two, four = peak_of_evaluation(tmp_path / "two", 2), peak_of_evaluation(tmp_path / "four", 4)
    assert two > IMAGE_BYTES  # the accounting sees a view's renders
    assert four <= two + IMAGE_BYTES / 4, f"peak {four / 2**20:.0f} MiB for 4 views vs {two / 2**20:.0f} MiB for 2"

    # The same accounting catches a full-size render kept per view.
    kept = []
    score_view = evaluation._score_view

    def keep_render(pipeline, view, *args):
        kept.append(pipeline.render(view.camera, view.exposure).hdr)
        return score_view(pipeline, view, *args)

    monkeypatch.setattr(evaluation, "_score_view", keep_render)
    leaking = peak_of_evaluation(tmp_path / "leak", 4)
    assert leaking >= two + 2 * IMAGE_BYTES
