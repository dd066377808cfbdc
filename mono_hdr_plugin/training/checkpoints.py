"""Checkpoints: written atomically, loaded with weights_only=True, versioned."""

import pickle
import warnings
from pathlib import Path
from typing import Any

import torch

from mono_hdr_plugin import __version__
from mono_hdr_plugin.data.io import atomic_path

CHECKPOINT_FORMAT = "mono-hdr-3d checkpoint"
ZIP_MAGIC = b"PK\x03\x04"
"""torch.save writes a zip archive; anything else is not a checkpoint of ours."""
CHECKPOINT_VERSION = 3
# Why each older version cannot be read, so the refusal names what went wrong.
RETIRED_VERSIONS = {
    1: "version 1 did not save state outside the parameters (3DGS's active SH degree): its 3DGS "
    "models would load and render without view-dependent colour",
    2: "version 2's L2H-CC had unconstrained weights; version 3 reads them as a non-decreasing converter "
    "(docs/method.md, 'A monotone L2H-CC'), so a version 2 model would render another HDR",
}


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable, or of another format version."""


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Save `payload` (state dicts, step, config JSON) with the format header, atomically and durably:
    a crash or a full disk leaves the previous file at `path` as it was (and raises OSError)."""
    payload = {
        "format": CHECKPOINT_FORMAT,
        "format_version": CHECKPOINT_VERSION,
        "package_version": __version__,
        **payload,
    }
    with atomic_path(path, durable=True) as temporary, open(temporary, "wb") as handle:
        writer = _RecordingWriter(handle)
        try:
            torch.save(payload, writer)  # type: ignore[arg-type]  # stub wants IO[bytes]; torch only writes, flushes
        except Exception as error:
            if writer.error is None:
                raise
            raise writer.error from error


class _RecordingWriter:
    """A file torch.save writes through, keeping the OSError of a failed write: torch reports a full
    disk as an opaque RuntimeError ("unexpected pos ..."), this says what happened (ENOSPC)."""

    def __init__(self, handle):
        self.handle, self.error = handle, None

    def write(self, data) -> int:
        try:
            return self.handle.write(data)
        except OSError as error:
            self.error = error
            raise

    def flush(self) -> None:
        self.handle.flush()


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Load a checkpoint safely (weights_only) and check that this version can read it."""
    path = Path(path)
    if path.is_dir():
        raise CheckpointError(
            f"checkpoint {path} is a folder; pass the .pt file a training run wrote (OUT/checkpoints/latest.pt)"
        )
    if not path.is_file():
        raise CheckpointError(
            f"checkpoint {path} does not exist; pass the .pt file a training run wrote under OUT/checkpoints/"
        )
    try:
        with open(path, "rb") as handle:
            magic = handle.read(len(ZIP_MAGIC))
    except OSError as error:
        raise CheckpointError(f"checkpoint {path} cannot be opened ({error.strerror}); fix its permissions") from error
    if magic != ZIP_MAGIC:
        reason = "the file is empty" if not magic else "it is not a PyTorch checkpoint file"
        raise CheckpointError(
            f"checkpoint {path} cannot be read ({reason}); it is truncated or not a mono-hdr-3d checkpoint"
        )
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols of files that are not ours
            warnings.simplefilter("ignore")
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        # torch's own text advises loading with weights_only=False: never do that with a file from elsewhere.
        raise CheckpointError(
            f"{path} is not a mono-hdr-3d checkpoint: it holds Python objects, not just tensors "
            "and numbers, and such files are never loaded (unpickling them can run code)"
        ) from None
    except Exception as error:
        raise CheckpointError(
            f"checkpoint {path} cannot be read ({_first_line(error)}); it is truncated or not a mono-hdr-3d checkpoint"
        ) from error
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path} is not a mono-hdr-3d checkpoint")
    version = payload.get("format_version")
    if version != CHECKPOINT_VERSION:
        reason = f" ({RETIRED_VERSIONS[version]})" if version in RETIRED_VERSIONS else ""
        raise CheckpointError(
            f"checkpoint {path} has format version {version} (written by mono-hdr-3d "
            f"{payload.get('package_version')}), this is mono-hdr-3d {__version__} which reads version "
            f"{CHECKPOINT_VERSION}{reason}: retrain, or install the version that wrote it"
        )
    return payload


def _first_line(error: Exception) -> str:
    """The exception's type and first line, without advice meant for trusted files."""
    lines = str(error).strip().splitlines()
    text = lines[0][:160] if lines and "weights_only" not in lines[0] else ""
    return f"{type(error).__name__}: {text}" if text else type(error).__name__
