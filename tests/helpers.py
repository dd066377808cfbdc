"""Test helpers shared by several test folders (imported as `from helpers import ...`)."""


class FakeClock:
    """perf_counter that advances a fixed amount per call: a step of the trainer reads it twice."""

    def __init__(self, seconds_per_call: float):
        self.now, self.seconds_per_call = 0.0, seconds_per_call

    def perf_counter(self) -> float:
        self.now += self.seconds_per_call
        return self.now
