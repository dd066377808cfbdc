"""Progress of long work (training, studio renders): how a duration reads, and plain lines in a log.

Where the output is not a terminal (a log file, CI) rich draws no progress bar until the work ends, so
`PlainProgressLines` prints a plain line at most every LOG_EVERY_SECONDS instead of staying silent.
"""

from __future__ import annotations

import time

from rich.console import Console

LOG_EVERY_SECONDS = 30.0


def duration_text(seconds: float | None) -> str:
    """`42 s`, `4 min 05 s`, `32 min`, `1 h 05 min`; `?` when not known yet. Seconds are dropped from
    10 minutes on, where an estimate is no better than a minute."""
    if seconds is None:
        return "?"
    whole = round(seconds)
    if whole < 60:
        return f"{whole} s"
    if whole < 600:
        return f"{whole // 60} min {whole % 60:02d} s"
    if whole < 3600:
        return f"{round(seconds / 60)} min"
    return f"{whole // 3600} h {whole % 3600 // 60:02d} min"


class PlainProgressLines:
    """Prints a progress line where the output is not a terminal, at most every LOG_EVERY_SECONDS (or
    always when asked: the first estimate); in a terminal only what is always printed."""

    def __init__(self, console: Console):
        self.console = console
        self.printed_at = time.monotonic()

    def print(self, text: str, always: bool = False) -> None:
        now = time.monotonic()
        if always or (not self.console.is_terminal and now - self.printed_at >= LOG_EVERY_SECONDS):
            self.printed_at = now
            self.console.print(text, markup=False, highlight=False)
