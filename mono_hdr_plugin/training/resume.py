"""Which settings a resumed run may change, and how a change is described; the data a saved model
may be scored on."""

import warnings
from pathlib import Path
from typing import Any

from mono_hdr_plugin.core.validation import FlagError, iter_flags
from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.training.checkpoints import CheckpointError
from mono_hdr_plugin.training.config import TrainConfig, step_limit


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
    "--eval-appearance",
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
    "--resolution",
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


def check_run_to_resume(config: TrainConfig) -> None:
    """--resume needs a checkpoint in --out; train takes no .pt file, so the fix is about --out or --resume."""
    checkpoint = config.out / "checkpoints" / "latest.pt"
    if not checkpoint.exists():
        raise CheckpointError(
            f"--resume: there is no run to continue in {config.out} ({checkpoint} does not exist): drop "
            "--resume to start a new run there, or point --out at the folder of the run to continue"
        )


def steps_left_note(config: TrainConfig, step: int, finished: bool, train_seconds: float) -> str | None:
    """What a resumed run at `step` has left to train: refused beyond --max-steps (the model asked for
    cannot be had; nothing is written), a note when its budget is reached (it trains nothing, keeps its
    checkpoint as it is and is only scored, as an evaluation that was interrupted needs), else None."""
    limit = step_limit(config)
    steps = f"--max-steps {limit}" + ("" if config.max_steps is not None else " (the default)")
    if limit is not None and step > limit:
        raise FlagError(
            f"the run in {config.out} is at step {step} > {steps}: nothing to train, and its checkpoint is "
            "kept as it is; raise --max-steps to train further, or score it with `mono-hdr eval --checkpoint "
            f"{config.out / 'checkpoints' / 'latest.pt'}`"
        )
    if not finished:
        return None
    reached = (
        f"step {step} = {steps}"
        if limit is not None and step >= limit
        else f"{train_seconds:.0f} s of training >= --max-seconds {config.max_seconds:g}"
    )
    return (
        f"note: the run in {config.out} is at {reached}: nothing to train (raise it to train further); its "
        "checkpoint is kept as it is and scored"
    )


def describe_data(name: str, source: str, train_views: int) -> str:
    return f"scene {name!r} ({source}, {train_views} training views)"


def check_scored_data(trained_on: dict | None, scene: SceneData, checkpoint: Path, flag: str) -> None:
    """A model scored on data other than its run's (`eval --data/--scene`, e.g. a held-out copy): a
    warning naming both; refused when the training views differ in number, as the model's per-view
    state (cameras, learned exposures) was made for its own views. `trained_on`: the checkpoint's
    "data" record (None in checkpoints that predate it)."""
    if not trained_on or trained_on["fingerprint"] == scene.fingerprint():
        return
    was = describe_data(trained_on["scene"], trained_on["source"], trained_on["train_views"])
    now = describe_data(scene.name, str(scene.metadata.get("source", "in memory")), len(scene.train))
    if trained_on["train_views"] != len(scene.train):
        raise FlagError(
            f"{flag}: {checkpoint} was trained on {was}, which does not fit {now}: pass {flag} a copy of "
            "the run's scene with its training views, or leave it out to score on the run's own data"
        )
    warnings.warn(f"{checkpoint} was trained on {was} and is scored on {now} ({flag})", stacklevel=2)
