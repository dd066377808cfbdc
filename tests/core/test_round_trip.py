"""Train, save, load, evaluate and render: a saved model must render exactly as the trained one.

A checkpoint that leaves out state outside the parameters (3DGS's active SH degree, a NeRF's
density grid) loads without error and then renders a different model; only comparing the
images and metrics of the trained and the loaded model catches that.
"""

import json

import numpy as np
import pytest
import register_backbone  # examples/, put on sys.path by conftest
import torch
from helpers import quiet_config

from backbones.gs import GaussianConfig
from backbones.nerf import GridFieldConfig, MlpFieldConfig, NerfConfig
from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.apps.render import render_checkpoint
from mono_hdr_plugin.data.io import read_exr
from mono_hdr_plugin.methods.base import method_names
from mono_hdr_plugin.training.evaluation import evaluate
from mono_hdr_plugin.training.trained import load_trained_model
from mono_hdr_plugin.training.trainer import Trainer

BACKBONE_CONFIGS = {
    "gs": lambda: GaussianConfig(random_init_points=400),
    "nerf-cpu": lambda: NerfConfig(
        field=GridFieldConfig(
            levels=2,
            min_resolution=4,
            max_resolution=8,
            hidden_width=16,
            min_step=0.125,
            max_samples_per_ray=16,
            occupancy_resolution=8,
            occupancy_update_every=2,
            rays_per_step=64,
            samples_per_step=512,
        )
    ),
    "nerf-paper": lambda: NerfConfig(
        field=MlpFieldConfig(
            width=32, coarse_samples=8, fine_samples=8, rays_per_step=64, density_activation="softplus"
        )
    ),
    "voxel-grid": lambda: register_backbone.VoxelGridConfig(resolution=12, samples_per_ray=24),
}
METRIC_KEYS = ("hdr_psnr", "hdr_ssim", "hdr_psnr_gt_max", "hdr_ssim_gt_max", "ldr_psnr", "ldr_ssim")


def trained(tmp_path, scene, case: str, method: str, steps: int = 8) -> tuple[Trainer, dict]:
    backbone_config = BACKBONE_CONFIGS[case]()
    config = quiet_config(
        backbone_config, tmp_path / "run", method, max_steps=steps, max_eval_views=2, save_renders=True
    )
    trainer = Trainer(config, case.split("-")[0] if case != "voxel-grid" else case, scene)
    return trainer, trainer.train()


def images(folder, pattern: str) -> dict[str, np.ndarray]:
    return {path.name: read_exr(path) for path in sorted(folder.glob(pattern))}


@pytest.mark.parametrize("method", method_names())
@pytest.mark.parametrize("case", sorted(BACKBONE_CONFIGS))
class TestSavedModelRendersAsTrained:
    def test_eval_and_render_of_checkpoint_equal_training(self, tmp_path, voxel_scene, case, method):
        trainer, metrics = trained(tmp_path, voxel_scene, case, method)
        checkpoint = trainer.checkpoint_path()
        trained_renders = images(tmp_path / "run" / "renders", "*_hdr.exr")
        assert len(trained_renders) == 2

        run = load_trained_model(checkpoint, scene=voxel_scene)
        again = evaluate(run.pipeline, voxel_scene, max_eval_views=2, render_dir=tmp_path / "eval" / "renders")
        for key in METRIC_KEYS:
            assert again[key] == pytest.approx(metrics[key], rel=1e-6, abs=1e-9), key
        eval_renders = images(tmp_path / "eval" / "renders", "*_hdr.exr")
        assert eval_renders.keys() == trained_renders.keys()
        for name, image in trained_renders.items():
            np.testing.assert_allclose(eval_renders[name], image, rtol=1e-6, atol=1e-7, err_msg=name)

        render_checkpoint(checkpoint, tmp_path / "render", max_views=2, scene=voxel_scene)
        rendered = images(tmp_path / "render", "*_hdr.exr")
        assert rendered.keys() == trained_renders.keys()
        for name, image in trained_renders.items():
            np.testing.assert_allclose(rendered[name], image, rtol=1e-6, atol=1e-7, err_msg=name)


class TestGaussianStateOutsideParameters:
    def test_active_sh_degree_and_density_statistics_survive_state_dict(self, tmp_path, voxel_scene):
        trainer, _ = trained(tmp_path, voxel_scene, "gs", "mono", steps=4)
        backbone = trainer.backbone
        assert backbone.active_sh_degree == 3  # 4 steps of a 4-step run: the ramp is done
        backbone.strategy_state["grad2d_sum"].uniform_()
        fresh = Trainer(trainer.config, "gs", voxel_scene).backbone
        assert fresh.active_sh_degree == 0
        fresh.load_state_dict(backbone.state_dict())
        assert fresh.active_sh_degree == 3
        torch.testing.assert_close(fresh.strategy_state["grad2d_sum"], backbone.strategy_state["grad2d_sum"])


class TestCommandLine:
    def test_eval_of_a_trained_3dgs_reproduces_its_metrics(self, tmp_path):
        """The user's report: `train gs` then `eval` of its checkpoint gave 10 dB less HDR PSNR."""
        out = tmp_path / "run"
        main(
            [
                "train",
                "gs",
                "--scene",
                "demo",
                "--max-steps",
                "30",
                "--out",
                str(out),
                "--quiet",
                "--max-eval-views",
                "2",
            ]
        )
        trained_metrics = json.loads((out / "metrics.json").read_text())
        main(["eval", "--checkpoint", str(out / "checkpoints" / "latest.pt"), "--out", str(tmp_path / "eval")])
        evaluated = json.loads((tmp_path / "eval" / "metrics.json").read_text())
        for key in METRIC_KEYS:
            assert evaluated[key] == pytest.approx(trained_metrics[key], rel=1e-6), key
        names = sorted(p.name for p in (tmp_path / "eval" / "renders").iterdir())
        assert names == sorted(p.name for p in (out / "renders").iterdir())
        assert all(name.split("_t")[0].isdigit() and ".png_" not in name for name in names), names
