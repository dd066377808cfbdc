"""Configs saved in checkpoints come back as they were trained, including those written before a
field with a new default behaviour existed."""

import json

from backbones.gs.model import GaussianConfig
from backbones.nerf.config import GridFieldConfig, MlpFieldConfig, NerfConfig
from mono_hdr_plugin.core.configs import config_from_dict, config_to_json


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
