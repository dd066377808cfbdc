"""Configs saved in checkpoints come back as they were trained, including those written before a
field with a new default behaviour existed, and before methods had options of their own."""

import json

from register_backbone import VoxelGridConfig

from backbones.gs.model import GaussianConfig
from backbones.nerf.config import GridFieldConfig, MlpFieldConfig, NerfConfig
from mono_hdr_plugin.core.configs import config_from_dict, config_to_json
from mono_hdr_plugin.methods.base import MethodOptions, build_method, method_config_for
from mono_hdr_plugin.methods.hdr_nerf import HdrNerfBaseline, HdrNerfOptions
from mono_hdr_plugin.training.checkpoints import load_checkpoint, save_checkpoint
from mono_hdr_plugin.training.config import saved_train_config, train_config_for
from mono_hdr_plugin.training.trained import load_trained_model
from mono_hdr_plugin.training.trainer import Trainer, build_trainer


def saved(config) -> dict:
    return json.loads(config_to_json(config))


class TestConfigFromDict:
    def test_round_trip(self):
        config = NerfConfig(field=GridFieldConfig(levels=5, l2h_input="activated", color_activation="softplus"))
        assert config_from_dict(NerfConfig, saved(config)) == config

    def test_the_paper_field_is_recognised(self):
        config = NerfConfig(field=MlpFieldConfig())
        assert isinstance(config_from_dict(NerfConfig, saved(config)).field, MlpFieldConfig)

    def test_a_config_saved_before_l2h_input_trains_l2h_on_the_colour(self):
        """Checkpoints written before the field existed trained L2H-CC on the sigmoid colour: the
        new default (the logit) would render their HDR wrongly."""
        values = saved(NerfConfig())
        del values["field"]["l2h_input"]
        rebuilt = config_from_dict(NerfConfig, values)
        assert isinstance(rebuilt.field, GridFieldConfig)
        assert rebuilt.field.l2h_input == "activated"
        assert GridFieldConfig().l2h_input == "raw"

    def test_other_absent_fields_take_their_default(self):
        values = saved(GaussianConfig(lr_opacities=0.5))
        del values["lr_opacities"]
        assert config_from_dict(GaussianConfig, values).lr_opacities == GaussianConfig().lr_opacities


# `hdr` as a run config saved it before methods had options of their own: HDR-NeRF's flags flat
# among the shared ones, for every method, and no "options".
OLD_HDR_NERF = {
    "method": "hdr-nerf",
    "hidden": 64,
    "use_ldr_loss": True,
    "use_hdr_loss": True,
    "use_h2l_loss": True,
    "alpha": 0.6,
    "beta": None,
    "loss": "auto",
    "dssim_weight": 0.2,
    "converter_lr": None,
    "unit_exposure_weight": 0.3,
    "unit_exposure_value": 0.73,
    "crf_warmup_steps": 100,
}
OLD_OPTIONS = HdrNerfOptions(unit_exposure_weight=0.3, unit_exposure_value=0.73, crf_warmup_steps=100)


class TestMethodOptions:
    def test_round_trip(self):
        config = train_config_for(VoxelGridConfig, "hdr-nerf")()
        config.hdr.options.crf_warmup_steps = 7
        assert saved_train_config(VoxelGridConfig, saved(config)) == config

    def test_a_config_saved_before_options_rebuilds_the_same_method(self):
        values = {**saved(train_config_for(VoxelGridConfig)()), "hdr": OLD_HDR_NERF}
        config = saved_train_config(VoxelGridConfig, values)
        assert type(config.hdr) is method_config_for("hdr-nerf") and config.hdr.hidden == 64
        method = build_method(config.hdr, "mse")
        assert type(method) is HdrNerfBaseline and method.options == OLD_OPTIONS
        assert method.learning_rate("method", 0, 1.0) == 0.01

    def test_a_method_without_options_ignores_the_old_flat_flags(self):
        values = {**saved(train_config_for(VoxelGridConfig)()), "hdr": {**OLD_HDR_NERF, "method": "mono"}}
        config = saved_train_config(VoxelGridConfig, values)
        assert config.hdr.method == "mono" and config.hdr.options == MethodOptions()

    def test_an_old_checkpoint_loads_and_resumes_with_its_values(self, tmp_path, voxel_scene):
        config = train_config_for(VoxelGridConfig, "hdr-nerf")(
            backbone=VoxelGridConfig(resolution=8, samples_per_ray=8),
            out=tmp_path / "run",
            quiet=True,
            save_renders=False,
            max_steps=1,
        )
        config.hdr.hidden, config.hdr.options = 64, OLD_OPTIONS
        trainer = Trainer(config, "voxel-grid", voxel_scene)
        trainer.train_step()
        trainer.save()
        path = trainer.checkpoint_path()
        payload = load_checkpoint(path)
        old = {**json.loads(payload["config"]), "hdr": OLD_HDR_NERF}
        save_checkpoint(path, {**payload, "config": json.dumps(old)})

        run = load_trained_model(path, scene=voxel_scene)
        assert run.pipeline.method.options == OLD_OPTIONS and run.config.hdr.options == OLD_OPTIONS
        config.resume = True
        resumed = build_trainer(config, "voxel-grid", voxel_scene)
        assert resumed.step == 1 and resumed._check_resumable(load_checkpoint(path)) == []
