"""The trainer's NaN/Inf guard, beyond tests/core/test_train.py::TestNanGuard (NaN loss, stop
after `nan_patience`, parameters untouched): non-finite gradients, the log line naming the
tensor, recovery after a transient failure, and the last good checkpoint after divergence."""

import math

import pytest
import torch
from hard_scenes import finite_parameters, make_scene, make_trainer

from mono_hdr_plugin.training.checkpoints import load_checkpoint
from mono_hdr_plugin.training.trainer import TrainingDiverged, build_trainer


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def poison_gradient(parameter: torch.Tensor, bad_calls: set[int]):
    """Make the gradient of `parameter` NaN on the listed backward passes (0-based)."""
    calls = {"count": 0}

    def hook(grad):
        index = calls["count"]
        calls["count"] += 1
        return grad * math.nan if index in bad_calls else grad

    return parameter.register_hook(hook)


def test_non_finite_gradient_with_finite_loss_is_skipped_and_named(tmp_path, scene):
    trainer = make_trainer(tmp_path, "voxel-grid", scene, max_steps=5)
    poison_gradient(trainer.backbone.density, {0})
    before = [p.detach().clone() for p in trainer.backbone.parameters()]
    record = trainer.train_step()
    assert math.isfinite(record["loss"]) and record["skipped"]
    resolution = trainer.backbone.config.resolution
    assert record["bad_tensors"] == [f"grad of grid[0] (1, {resolution}, {resolution}, {resolution})"]
    assert all(torch.equal(a, b) for a, b in zip(before, trainer.backbone.parameters()))
    assert all(p.grad is None for p in trainer.backbone.parameters())  # no stale NaN gradient left
    assert not trainer.train_step()["skipped"]


def test_transient_failures_are_logged_skipped_and_training_recovers(tmp_path, scene, capsys):
    trainer = make_trainer(tmp_path, "voxel-grid", scene, max_steps=12, nan_patience=3)
    poison_gradient(trainer.backbone.color_logits, {3, 4, 8})  # 2 then 1 consecutive: below patience
    metrics = trainer.train()
    log = capsys.readouterr().err
    assert log.count("step skipped") == 3
    assert "step 4: non-finite grad of grid[1]" in log and "step 9: non-finite grad of grid[1]" in log
    assert metrics["steps"] == 12 and math.isfinite(metrics["ldr_psnr"])
    assert not finite_parameters(trainer.backbone, trainer.method)
    # Adam never saw the skipped steps: its step count is the number of good steps
    state = trainer.optimizer.state[trainer.backbone.density]
    assert int(state["step"]) == 12 - 3


def test_infinite_loss_counts_like_nan(tmp_path, scene, monkeypatch):
    trainer = make_trainer(tmp_path, "voxel-grid", scene, max_steps=10, nan_patience=2)
    original = trainer.method.losses
    monkeypatch.setattr(trainer.method, "losses", lambda *a: {k: v * math.inf for k, v in original(*a).items()})
    with pytest.raises(TrainingDiverged, match=r"2 consecutive steps.*\(last: loss.*stopped at step 2"):
        trainer.train()


def test_diverged_run_keeps_last_good_checkpoint_loadable_and_resumable(tmp_path, scene):
    trainer = make_trainer(tmp_path, "voxel-grid", scene, max_steps=30, nan_patience=4, checkpoint_every=5)
    poison_gradient(trainer.backbone.density, set(range(12, 1000)))  # good until step 12, then always bad
    with pytest.raises(TrainingDiverged) as error:
        trainer.train()
    message = str(error.value)
    assert "4 consecutive steps" in message and "grad of grid[0]" in message
    assert str(trainer.checkpoint_path()) in message and "lower the learning rates" in message
    payload = load_checkpoint(trainer.checkpoint_path())
    assert payload["step"] == 10  # the last multiple of checkpoint_every before the failures
    for name, tensor in payload["pipeline"].items():
        if isinstance(tensor, torch.Tensor):  # not the extra state (the radiance calibration)
            assert torch.isfinite(tensor).all(), name
    config = trainer.config
    config.resume = True
    resumed = build_trainer(config, "voxel-grid", scene)
    assert resumed.step == 10
    metrics = resumed.train()
    assert metrics["steps"] == 30 and math.isfinite(metrics["ldr_psnr"])


def test_patience_of_one_stops_at_the_first_bad_step(tmp_path, scene):
    trainer = make_trainer(tmp_path, "voxel-grid", scene, max_steps=10, nan_patience=1)
    poison_gradient(trainer.backbone.density, {2})
    with pytest.raises(TrainingDiverged, match="1 consecutive steps.*stopped at step 3"):
        trainer.train()


def test_nan_in_training_data_is_refused_before_training(scene):
    from mono_hdr_plugin.data.dataset import View

    view = scene.train[0]
    hdr = view.hdr.clone()
    hdr[3, 4, 1] = math.nan
    with pytest.raises(ValueError, match=f"{view.name}: HDR ground truth contains NaN or Inf"):
        View(camera=view.camera, image=view.image, exposure=view.exposure, view_id=0, name=view.name, hdr=hdr)
    image = view.image.clone()
    image[0, 0, 0] = math.inf
    with pytest.raises(ValueError, match=f"{view.name}: image contains NaN or Inf"):
        View(camera=view.camera, image=image, exposure=view.exposure, view_id=0, name=view.name)
