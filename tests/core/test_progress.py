"""Training's progress where the output is not a terminal (a log file, CI): plain lines, not silence."""

from known_render import KnownRenderConfig
from test_calibration import known_scene

from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.hooks import ProgressBar
from mono_hdr_plugin.training.trainer import Trainer


class TestProgressInALog:
    def test_plain_lines_while_training(self, tmp_path, capsys, monkeypatch):
        monkeypatch.setattr(ProgressBar, "LOG_EVERY_SECONDS", 0.0)  # a line after every step
        config = train_config_for(KnownRenderConfig)(
            backbone=KnownRenderConfig(), out=tmp_path / "run", quiet=False, max_steps=3, save_renders=False
        )
        Trainer(config, "known-render", known_scene()).train()
        err = capsys.readouterr().err
        assert "training known-render/mono from step 0" in err
        assert [line.split(":")[0] for line in err.splitlines() if line.startswith("step ")] == [
            "step 1/3",
            "step 2/3",
            "step 3/3",
        ]
