"""Which settings a resumed run may change, and how a change is described."""

from pathlib import Path
from typing import Any

from mono_hdr_plugin.core.validation import iter_flags
from mono_hdr_plugin.training.config import TrainConfig


class ResumeMismatch(ValueError):
    """--resume with settings that would continue a different model or data than the checkpoint's."""


# Flags of a run that may change when it is resumed (the schedule, the output, logging).
RESUME_FREE_FLAGS = {
    "--max-steps",
    "--max-seconds",
    "--out",
    "--resume",
    "--overwrite",
    "--eval-every",
    "--checkpoint-every",
    "--max-eval-views",
    "--save-renders",
    "--nan-patience",
    "--quiet",
    "--seed",
    "--preset",
    "--viewer",
    "--viewer-port",
    "--viewer-host",
}
# The data flags count through the data itself; the flags that make a resumed run a different model
# are the method's (HdrMethod.resume_identity_flags).
DATA_FLAGS = {
    "--data",
    "--scene",
    "--layout",
    "--protocol",
    "--exposure-index",
    "--fixed-exposure",
    "--downscale",
    "--exposure-seed",
}


def changed_flags(before: TrainConfig, after: TrainConfig) -> dict[str, tuple[Any, Any]]:
    """{flag: (old, new)} of the flags that differ between two run configs (paths compared resolved,
    so `./scene` and `/abs/scene` are one), leaving out RESUME_FREE_FLAGS."""

    def comparable(value: Any) -> Any:
        return str(Path(value).resolve()) if isinstance(value, Path) else value

    old = {flag: value for flag, value, _ in iter_flags(before)}
    new = {flag: value for flag, value, _ in iter_flags(after)}
    return {
        flag: (old.get(flag), new.get(flag))
        for flag in sorted(old.keys() | new.keys())
        if flag not in RESUME_FREE_FLAGS and comparable(old.get(flag)) != comparable(new.get(flag))
    }


def describe_change(flag: str, change: tuple[Any, Any]) -> str:
    return f"{flag} {change[1]} (was {change[0]})"
