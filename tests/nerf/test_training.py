"""Two real training steps of every method with the NeRF backbone (both fields), via the lead's Trainer."""

import math

import pytest
import torch
from helpers import quiet_config
from nerf_scenes import tiny_config

from backbones.nerf import NerfBackbone
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.methods.base import method_names
from mono_hdr_plugin.training.trainer import Trainer


def nerf_trainer(tmp_path, scene, field: str, method: str) -> Trainer:
    config = quiet_config(tiny_config(field), tmp_path / "run", method, max_steps=2)
    return Trainer(config, "nerf", scene)


class TestTwoStepsOfEveryMethod:
    @pytest.mark.parametrize("field", ["paper", "cpu"])
    @pytest.mark.parametrize("method", method_names())
    def test_two_steps(self, tmp_path, voxel_scene, field, method):
        trainer = nerf_trainer(tmp_path, voxel_scene, field, method)
        before = [p.detach().clone() for p in trainer.backbone.parameters()]
        records = [trainer.train_step() for _ in range(2)]
        assert all(math.isfinite(r["loss"]) and not r["skipped"] for r in records)
        assert any(not torch.equal(a, b) for a, b in zip(before, trainer.backbone.parameters()))
        if field == "paper" and records[0].get("ldr") is not None:
            assert "ldr_aux0" in records[0]  # the coarse network is supervised too

    def test_chunked_full_render_has_image_shape(self, tmp_path, voxel_scene):
        trainer = nerf_trainer(tmp_path, voxel_scene, "cpu", "mono")
        trainer.backbone.render_chunk = 50
        view = voxel_scene.test[0]
        output = trainer.pipeline.render(view.camera, view.exposure)
        assert output.ldr.shape == output.hdr.shape == (view.camera.height, view.camera.width, 3)
        assert torch.isfinite(output.hdr).all()


class TestCheckpoint:
    def test_resume_restores_density_grid_and_next_loss(self, tmp_path, voxel_scene):
        trainer = nerf_trainer(tmp_path, voxel_scene, "cpu", "mono")
        for _ in range(2):
            trainer.train_step()
        trainer.save()
        saved_batch = trainer.backbone.pixel_batch
        expected = trainer.train_step()["loss"]
        resumed = nerf_trainer(tmp_path, voxel_scene, "cpu", "mono")
        resumed.restore(torch.load(trainer.checkpoint_path(), weights_only=True))
        assert resumed.backbone.occupancy.filled
        assert resumed.backbone.pixel_batch == saved_batch
        assert resumed.train_step()["loss"] == pytest.approx(expected, rel=1e-5)


@pytest.mark.slow
class TestCpuFieldLearnsTheDemoScene:
    def test_hdr_psnr_rises(self, tmp_path):
        scene = load_scene(DataConfig(scene="demo"))
        config = quiet_config(NerfBackbone.presets()["cpu"], tmp_path / "run", max_steps=400, max_eval_views=2)
        trainer = Trainer(config, "nerf", scene)
        for _ in range(50):
            trainer.train_step()
        early = trainer.evaluate()["hdr_psnr"]
        while trainer.step < config.max_steps:
            trainer.train_step()
        late = trainer.evaluate()["hdr_psnr"]
        assert late > early + 0.5


@pytest.mark.slow
def test_cpu_preset_beats_the_old_fast_field_in_200_steps(tmp_path):
    """The cpu preset, 200 steps of Mono-HDR on the 16 px capture of examples/register_backbone.py,
    passes 18.0 dB HDR PSNR on the mean of seeds 0, 1 and 3. The fast field it replaced (commit
    27fdab5, preset fast) reached 17.43 dB in 200 steps with seed 3. One seed is not enough: a
    200-step run moves by about a dB with the rays it draws (seeds 3 / 0 / 1 gave 17.98 / 18.32 /
    18.96 dB after issue 31 put each view's brightest pixel in every batch; seed 3 gave 18.48 before)."""
    import register_backbone

    scene = register_backbone.make_capture(size=16, views=8)
    scores = []
    for seed in (0, 1, 3):
        config = quiet_config(NerfBackbone.presets()["cpu"], tmp_path / f"run{seed}", max_steps=200, seed=seed)
        scores.append(Trainer(config, "nerf", scene).train()["hdr_psnr"])
    assert sum(scores) / len(scores) > 18.0, f"HDR PSNR of seeds 0, 1, 3: {scores}"
