"""Training's progress where the output is not a terminal (a log file, CI): plain lines, not silence."""

import io
from types import SimpleNamespace

import pytest
import register_backbone
from helpers import FakeClock
from known_render import KnownRenderConfig
from rich.console import Console
from test_calibration import known_scene

from mono_hdr_plugin.core import progress
from mono_hdr_plugin.core.progress import PlainProgressLines, duration_text
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.hooks import EvaluateEvery, ProgressBar, TrainingHook, seconds_left
from mono_hdr_plugin.training.pyramid import ImagePyramid
from mono_hdr_plugin.training.trainer import Trainer


class TestProgressInALog:
    def test_plain_lines_while_training(self, tmp_path, capsys, monkeypatch):
        monkeypatch.setattr(progress, "LOG_EVERY_SECONDS", 0.0)  # a line after every step
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


class TestPlainProgressLines:
    """At most a line every LOG_EVERY_SECONDS where the output is not a terminal; in a terminal (which has
    the progress bar) only the lines asked for always."""

    def lines(self, monkeypatch, is_terminal: bool, seconds_apart: list[float], always: int = -1) -> list[str]:
        now = [0.0]
        monkeypatch.setattr(progress.time, "monotonic", lambda: now[0])
        console = Console(file=io.StringIO(), force_terminal=is_terminal, width=200)
        lines = PlainProgressLines(console)
        for index, seconds in enumerate(seconds_apart):
            now[0] += seconds
            lines.print(f"line {index}", always=index == always)
        return console.file.getvalue().splitlines()

    def test_a_log_gets_a_line_every_interval(self, monkeypatch):
        # 10 s apart: due at 30 s, then 30 s after that line, not after the start
        assert self.lines(monkeypatch, False, [10.0] * 7) == ["line 2", "line 5"]

    def test_a_line_always_printed_restarts_the_interval(self, monkeypatch):
        assert self.lines(monkeypatch, False, [10.0] * 7, always=1) == ["line 1", "line 4"]

    def test_a_terminal_gets_only_the_lines_always_printed(self, monkeypatch):
        assert self.lines(monkeypatch, True, [40.0] * 3, always=1) == ["line 1"]


class TestTimeLeft:
    """The time left, under a fake clock: every step takes 0.5 s, the clock advancing 0.5 s a read."""

    @pytest.fixture
    def clock(self, monkeypatch):
        import mono_hdr_plugin.training.trainer as trainer_module

        clock = FakeClock(0.5)
        monkeypatch.setattr(trainer_module.time, "perf_counter", clock.perf_counter)
        self.monkeypatch = monkeypatch
        return clock

    def run(self, tmp_path, clock, evaluation_seconds: float = 0.0, **flags) -> list[float | None]:
        """seconds_left after every step of a run with `flags`; an evaluation takes 0.5 + `evaluation_seconds`."""
        import mono_hdr_plugin.training.trainer as trainer_module

        evaluate = trainer_module.evaluate

        def slow_evaluate(*args, **kwargs):
            clock.now += evaluation_seconds
            return evaluate(*args, **kwargs)

        config = train_config_for(KnownRenderConfig)(
            backbone=KnownRenderConfig(), out=tmp_path / "run", quiet=True, save_renders=False, **flags
        )
        trainer = Trainer(config, "known-render", known_scene())
        self.monkeypatch.setattr(trainer_module, "evaluate", slow_evaluate)
        left = Recorder()
        hooks = [EvaluateEvery(config.eval_every)] if config.eval_every else []
        trainer.fit([*hooks, left])
        return left.values

    def test_max_steps(self, tmp_path, clock):
        assert self.run(tmp_path, clock, max_steps=6) == pytest.approx([2.5, 2.0, 1.5, 1.0, 0.5, 0.0])

    def test_evaluations_still_due_count(self, tmp_path, clock):
        """--eval-every 2 of 7 steps evaluates at steps 2, 4 and 6; each evaluation takes 3.5 s."""
        left = self.run(tmp_path, clock, evaluation_seconds=3.0, max_steps=7, eval_every=2)
        # before the first evaluation its cost is unknown; after it, the ones at 4 and 6, then at 6, then none
        assert left == pytest.approx([3.0, 2.5 + 2 * 3.5, 2.0 + 2 * 3.5, 1.5 + 3.5, 1.0 + 3.5, 0.5, 0.0])

    def test_max_seconds(self, tmp_path, clock):
        assert self.run(tmp_path, clock, max_seconds=4.0) == pytest.approx([3.5, 3.0, 2.5, 2.0, 1.5, 1.0, 0.5, 0.0])

    def test_both_limits_whichever_first(self, tmp_path, clock):
        assert self.run(tmp_path, clock, max_steps=3, max_seconds=100.0) == pytest.approx([1.0, 0.5, 0.0])

    def test_the_log_line_says_it(self, tmp_path, capsys, monkeypatch, clock):
        monkeypatch.setattr(progress, "LOG_EVERY_SECONDS", 0.0)
        config = train_config_for(KnownRenderConfig)(
            backbone=KnownRenderConfig(), out=tmp_path / "run", quiet=False, max_steps=3, save_renders=False
        )
        Trainer(config, "known-render", known_scene()).fit([ProgressBar()])
        lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("step ")]
        assert [line.rsplit(", ", 1)[1] for line in lines] == ["about 1 s left", "about 0 s left", "about 0 s left"]

    @pytest.mark.parametrize(
        "seconds, text",
        [
            (None, "?"),
            (42.4, "42 s"),
            (245, "4 min 05 s"),
            (599.4, "9 min 59 s"),
            (1935, "32 min"),
            (3900, "1 h 05 min"),
        ],
    )
    def test_duration_text(self, seconds, text):
        assert duration_text(seconds) == text


class TestTimeLeftOfAPyramid:
    """3 levels over 8 steps, the first half coarse: levels 2, 2, 1, 1, 0, 0, 0, 0."""

    def trainer_after_two_steps(
        self, whole_images: bool, region_pixels: int | None = None, train_seconds: float = 0.125
    ) -> SimpleNamespace:
        views = register_backbone.make_capture(size=64, views=2).train
        return SimpleNamespace(
            step=2,
            train_seconds=train_seconds,  # default: two steps at 1/16 of the pixels of a 1 s full-size step
            run_length=8,
            pyramid=ImagePyramid(views, 3, 0.5, whole_images, region_pixels),
            config=SimpleNamespace(max_seconds=None, eval_every=0),
            evaluation_seconds=[],
        )

    def test_coarse_steps_do_not_promise_a_short_run(self):
        assert seconds_left(self.trainer_after_two_steps(True)) == pytest.approx(2 * 0.25 + 4 * 1.0)

    def test_regions_cap_the_pixels_of_every_level(self):
        """--region-pixels 1024 on 64 px views: levels of 256, 1024 and 1024 px; two 16 px steps at a
        quarter of a 1 s full-size step, then 2 + 4 steps at 1 s."""
        trainer = self.trainer_after_two_steps(True, region_pixels=1024, train_seconds=0.5)
        assert seconds_left(trainer) == pytest.approx(6 * 1.0)

    def test_ray_batches_cost_the_same_at_every_level(self):
        assert seconds_left(self.trainer_after_two_steps(False)) == pytest.approx(6 * 0.0625)


class Recorder(TrainingHook):
    def __init__(self):
        self.values: list[float | None] = []

    def after_step(self, trainer, record) -> None:
        self.values.append(seconds_left(trainer))
