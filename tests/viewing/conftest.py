"""Small trained models for the viewer, video and export tests, trained here in seconds."""

import pytest
import register_backbone  # noqa: F401 - registers voxel-grid (examples/, on sys.path via the top conftest)
from helpers import quiet_config, tiny_builtin_scenes

from mono_hdr_plugin.training.trained import TrainedModel
from mono_hdr_plugin.training.trainer import Trainer


def train_model(
    tmp_path, scene, backbone_name: str, backbone_config, method: str = "mono", steps: int = 20
) -> tuple[Trainer, TrainedModel]:
    """A Trainer after `steps` steps (checkpoint written) and the same model as the viewer loads it."""
    config = quiet_config(backbone_config, tmp_path / "run", method, max_steps=steps, max_eval_views=1)
    trainer = Trainer(config, backbone_name, scene)
    trainer.train()
    trainer.pipeline.eval()
    model = TrainedModel(
        pipeline=trainer.pipeline,
        scene=scene,
        config=trainer.config,
        step=trainer.step,
        train_seconds=trainer.train_seconds,
    )
    return trainer, model


@pytest.fixture(scope="session")
def voxel_mono(tmp_path_factory, voxel_scene, voxel_backbone_config):
    """Mono-HDR on the example voxel-grid backbone, 20 steps."""
    return train_model(tmp_path_factory.mktemp("voxel-mono"), voxel_scene, "voxel-grid", voxel_backbone_config)[1]


@pytest.fixture(scope="session")
def voxel_crf(tmp_path_factory, voxel_scene, voxel_backbone_config):
    """The HDR-NeRF baseline (a learned camera response) on the voxel-grid backbone, 20 steps."""
    return train_model(
        tmp_path_factory.mktemp("voxel-crf"), voxel_scene, "voxel-grid", voxel_backbone_config, method="hdr-nerf"
    )[1]


@pytest.fixture(scope="session")
def demo_voxel_checkpoint(tmp_path_factory, studio_cache):
    """A voxel-grid checkpoint of the tiny variant of the built-in demo scene, as the command line
    writes it (set up before the tests' autouse fixture, so it enters the tiny scenes itself)."""
    from mono_hdr_plugin.apps.cli import main

    out = tmp_path_factory.mktemp("demo-voxel") / "run"
    with tiny_builtin_scenes():
        main(
            ["train", "voxel-grid", "--scene", "demo", "--max-steps", "3", "--out", str(out), "--quiet"]
            + ["--max-eval-views", "1", "--no-save-renders", "--backbone.resolution", "8"]
            + ["--backbone.samples-per-ray", "8"]
        )
    return out / "checkpoints" / "latest.pt"
