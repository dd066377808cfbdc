"""The run-length estimate of a run under --max-seconds (Trainer._update_run_length), on a stand-in
trainer whose step times and clock the test sets: when it estimates, what, and when it tells the backbone."""

from collections import deque
from types import SimpleNamespace

import pytest

from mono_hdr_plugin.training.trainer import RUN_LENGTH_EVERY, RUN_LENGTH_WARMUP, Trainer


def stand_in(step: int, seconds_per_step: float, budget: float, run_length: int, max_steps: int | None = None):
    told: list[int] = []
    trainer = SimpleNamespace(
        config=SimpleNamespace(max_seconds=budget, max_steps=max_steps),
        step=step,
        recent_step_seconds=deque([seconds_per_step] * min(step, 50)),
        train_seconds=step * seconds_per_step,
        run_length=run_length,
        pipeline=SimpleNamespace(set_run_length=told.append),
    )
    return trainer, told


class TestUpdateRunLength:
    def test_estimates_after_the_warm_up_and_then_every_so_many_steps(self):
        assert (RUN_LENGTH_WARMUP, RUN_LENGTH_EVERY) == (5, 25)
        estimated_at = []
        for step in range(1, 81):
            trainer, told = stand_in(step, 0.5, budget=1000.0, run_length=10**6)  # far off: any estimate moves it
            Trainer._update_run_length(trainer)
            estimated_at += [step] if told else []
        assert estimated_at == [5, 25, 50, 75]

    def test_the_steps_that_fit_in_the_time_left(self):
        # step 25 at 0.5 s a step: 12.5 s spent, 87.5 s left = 175 more steps
        trainer, told = stand_in(25, 0.5, budget=100.0, run_length=3000)
        Trainer._update_run_length(trainer)
        assert told == [200] and trainer.run_length == 200

    def test_a_spent_budget_ends_at_the_next_step(self):
        trainer, told = stand_in(50, 0.5, budget=20.0, run_length=3000)  # 25 s spent of 20
        Trainer._update_run_length(trainer)
        assert told == [51]

    def test_max_steps_caps_the_estimate(self):
        trainer, told = stand_in(25, 0.5, budget=100.0, run_length=3000, max_steps=120)
        Trainer._update_run_length(trainer)
        assert told == [120]

    @pytest.mark.parametrize(
        "budget, run_length, moved",
        [
            (102.0, 200, False),  # estimate 204: exactly 2 % of 200 away
            (102.5, 200, True),  # 205: 2.5 %
            (100.0, 197, False),  # 200: 1.5 % of 197
            (100.0, 203, False),
            (100.0, 195, True),  # 2.6 %
        ],
    )
    def test_only_an_estimate_more_than_two_percent_away_is_told(self, budget, run_length, moved):
        trainer, told = stand_in(25, 0.5, budget=budget, run_length=run_length)
        expected = 25 + int((budget - 12.5) / 0.5)
        Trainer._update_run_length(trainer)
        assert told == ([expected] if moved else []) and trainer.run_length == (expected if moved else run_length)

    def test_without_a_time_budget_nothing_is_estimated(self):
        trainer, told = stand_in(25, 0.5, budget=None, run_length=10**6)
        Trainer._update_run_length(trainer)
        assert told == []
