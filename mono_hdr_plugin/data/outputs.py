"""An output folder is a run: one writer at a time, nothing of an earlier run replaced unasked,
and nothing outside the folder, or holding the inputs, ever removed (docs/robustness.md).

    with claim_output(out, "train", owned=TRAIN_OUTPUTS, inputs=[data], overwrite=False, keep=resume) as claim:
        ...                       # load the data, build the model: nothing is removed yet
        claim.clear_previous()    # --overwrite: the earlier run's outputs go now, just before writing
        ...                       # write checkpoints/, renders/, metrics.json

The claim is a small JSON file in the folder, RUN_FILE, naming the command, its PID and host. It is
locked (flock) while the command runs, so a second command on the same folder is refused with the
first one's PID and host, and it stays afterwards as the mark of a mono-hdr output: --overwrite
removes nothing from a folder without it. A claim left by a process that died (SIGKILL, power loss)
is no longer locked and is taken over with a note; a claim from another host cannot be checked
from here and is refused. Temporary files of an interrupted atomic write (`.<name>.tmp-<pid>.<ext>`)
are removed when the next command claims the folder.
"""

import contextlib
import fcntl
import json
import os
import re
import shutil
import socket
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

from rich.console import Console

from mono_hdr_plugin.data.errors import os_error_fix

RUN_FILE = ".mono-hdr-run.json"
TEMPORARY_FILE = re.compile(r"^\..+\.tmp-(\d+)(\.[^.]+)?$")
"""Names `data.io.atomic_path` gives its temporary files."""

console = Console(stderr=True, soft_wrap=True)


class OutputError(RuntimeError):
    """An output folder that cannot be used as asked: busy, holding another run, not writable, or
    an --overwrite that would remove something it must not."""


def _describe(claim: dict | None) -> str:
    if not claim:
        return "another mono-hdr command (its claim file is still being written)"
    started = claim.get("started")
    when = (
        time.strftime(" since %Y-%m-%d %H:%M:%S", time.localtime(started)) if isinstance(started, (int, float)) else ""
    )
    return (
        f"`mono-hdr {claim.get('command', '?')}` (PID {claim.get('pid', '?')} on host {claim.get('host', '?')}{when})"
    )


def _read_claim(handle) -> dict | None:
    """The claim in the file (None when empty; {} when unreadable)."""
    handle.seek(0)
    text = handle.read()
    if not text.strip():
        return None
    try:
        claim = json.loads(text)
    except ValueError:
        return {}
    return claim if isinstance(claim, dict) else {}


def _write_claim(handle, claim: dict) -> None:
    handle.seek(0)
    handle.truncate()
    handle.write(json.dumps(claim) + "\n")
    handle.flush()
    os.fsync(handle.fileno())


def _entry_name(path: Path) -> str:
    return path.name + ("/" if path.is_dir() and not path.is_symlink() else "")


def _existing_outputs(folder: Path, owned: tuple[str, ...] | None) -> list[Path]:
    """The owned entries present in `folder` (owned None: every entry but the claim file)."""
    if owned is None:
        return sorted(p for p in folder.iterdir() if p.name != RUN_FILE)
    return [folder / name for name in owned if (folder / name).exists() or (folder / name).is_symlink()]


def _within(path: Path, folder: Path) -> bool:
    return path == folder or path.is_relative_to(folder)


def check_not_inputs(target: Path, inputs: Iterable[Path | None], action: str = "--overwrite would remove") -> None:
    """Refuse to remove `target` when it is, holds, or lies inside one of the inputs."""
    # A symbolic link is removed itself, never followed.
    resolved = target.parent.resolve() / target.name if target.is_symlink() else target.resolve()
    for source in inputs:
        if source is None:
            continue
        source_resolved = Path(source).resolve()
        if _within(source_resolved, resolved) or _within(resolved, source_resolved):
            relation = "holds" if _within(source_resolved, resolved) else "lies inside"
            raise OutputError(
                f"{action} {target}, which {relation} the input {source}; nothing was removed: "
                "choose an output folder apart from your inputs"
            )


def check_replaceable(folder: Path, marker: Path, inputs: Iterable[Path | None], action: str) -> None:
    """Before a whole existing, non-empty `folder` is replaced (`action`, e.g. "--overwrite replaces"):
    it must not hold or lie inside an input, and must be one this command wrote (`marker` inside it)."""
    if not folder.is_dir() or not any(folder.iterdir()):
        return
    check_not_inputs(folder, inputs, action)
    if not marker.is_file():
        raise OutputError(
            f"{action} {folder}, which this command did not write (it has no {marker.name}); nothing "
            "was removed: choose a new --out, or remove the folder yourself"
        )


def plan_output(
    folder: Path,
    command: str,
    owned: tuple[str, ...] | None,
    inputs: Iterable[Path | None],
    overwrite: bool,
    keep: bool,
    previous: dict | None,
    keep_hint: str = "",
) -> list[Path]:
    """What has to go before `command` writes `folder` (nothing when no earlier output is in the way).

    keep: continue the earlier output in place: train --resume (its checkpoint is checked when it is
    loaded), or a command whose outputs add up (render). Refused: a folder mono-hdr did not write;
    for whole-folder outputs, another command's folder; an earlier output without --overwrite; an
    --overwrite that would remove something outside the folder or holding an input."""
    folder = Path(folder)
    existing = _existing_outputs(folder, owned) if folder.is_dir() else []
    if not existing or (keep and owned is not None):
        return []
    listing = ", ".join(_entry_name(p) for p in existing[:5]) + (" ..." if len(existing) > 5 else "")
    if previous is None:
        raise OutputError(
            f"--out {folder} holds {listing}, which mono-hdr did not write (no {RUN_FILE}); nothing "
            "is replaced there, even with --overwrite: choose another --out"
        )
    earlier = previous.get("command", "?")
    if owned is None and earlier != command:
        raise OutputError(
            f"--out {folder} holds the output of `mono-hdr {earlier}`; `mono-hdr {command}` writes "
            "into a folder of its own: choose another --out"
        )
    if keep:
        return []
    if not overwrite:
        raise OutputError(
            f"--out {folder} holds the output of an earlier `mono-hdr {earlier}` ({listing}); "
            f"{keep_hint}pass --overwrite to replace it, or choose another --out"
        )
    root, inputs = folder.resolve(), list(inputs)
    for path in existing:
        location = path.parent.resolve() / path.name
        if not location.is_relative_to(root) or location == root:
            raise OutputError(f"--overwrite would remove {path}, outside {folder}; nothing was removed")
        check_not_inputs(path, inputs)
    return existing


def check_output(
    folder: Path,
    command: str,
    owned: tuple[str, ...] | None,
    inputs: Iterable[Path | None] = (),
    overwrite: bool = False,
    keep: bool = False,
    keep_hint: str = "",
) -> None:
    """The read-only part of `claim_output`, for refusing early (before data is loaded): --out is
    not a file, and no earlier output is in the way. `claim_output` checks again under its lock."""
    folder = Path(folder)
    _check_is_folder(folder)
    claim_file = folder / RUN_FILE
    previous = None
    if claim_file.is_file():
        with open(claim_file) as handle:
            previous = _read_claim(handle)
    plan_output(folder, command, owned, inputs, overwrite, keep, previous, keep_hint)


def _check_is_folder(folder: Path) -> None:
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"--out {folder} is a file, not a folder; pass a folder path (it is created if missing)")


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_interrupted_writes(folder: Path, owned: tuple[str, ...] | None) -> list[Path]:
    """Remove the temporary files an interrupted atomic write left in `folder` (and in the owned
    subfolders, or everywhere below it when it owns the whole folder). A file whose writer still
    runs is left alone."""
    roots = [folder] + ([folder / name for name in owned if (folder / name).is_dir()] if owned is not None else [])
    removed = []
    for root in roots:
        candidates = root.rglob(".*.tmp-*") if owned is None else root.glob(".*.tmp-*")
        for path in candidates:
            match = TEMPORARY_FILE.match(path.name)
            if match and path.is_file() and not path.is_symlink() and not _process_alive(int(match.group(1))):
                path.unlink(missing_ok=True)
                removed.append(path)
    return removed


class OutputClaim:
    """A claimed output folder and what --overwrite will remove from it."""

    def __init__(self, folder: Path, removals: list[Path]):
        self.folder, self.removals = folder, removals

    def clear_previous(self) -> None:
        """Remove the earlier output --overwrite replaces; called once the new output is ready to be
        written, so a command that fails while loading its inputs leaves the earlier one in place."""
        for path in self.removals:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink(missing_ok=True)
        self.removals = []


def _open_claim_file(folder: Path):
    try:
        folder.mkdir(parents=True, exist_ok=True)
        return os.fdopen(os.open(folder / RUN_FILE, os.O_RDWR | os.O_CREAT, 0o644), "r+")
    except OSError as error:
        raise OutputError(f"--out {folder} cannot be written ({error.strerror}); {os_error_fix(error)}") from error


def _lock(folder: Path):
    """The claim file, open and flock-ed (OutputError naming the holder when another process has it).
    A file removed between opening and locking (a failed claim cleaning up) is opened again."""
    for _ in range(10):
        handle = _open_claim_file(folder)
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_claim(handle)
            handle.close()
            raise OutputError(
                f"--out {folder} is being written by {_describe(holder)}; wait for it to finish or choose another --out"
            ) from None
        except OSError as error:  # a file system without locks (some network mounts): go on, and say so
            console.print(
                f"note: {folder}: this file system cannot lock files ({error.strerror}); a second command "
                "writing this folder at the same time would not be noticed",
                markup=False,
            )
            return handle
        with contextlib.suppress(FileNotFoundError):
            if os.stat(folder / RUN_FILE).st_ino == os.fstat(handle.fileno()).st_ino:
                return handle
        handle.close()
    raise OutputError(f"--out {folder}: its claim file keeps disappearing; is another program removing it?")


@contextlib.contextmanager
def claim_output(
    folder: Path,
    command: str,
    owned: tuple[str, ...] | None,
    inputs: Iterable[Path | None] = (),
    overwrite: bool = False,
    keep: bool = False,
    keep_hint: str = "",
) -> Iterator[OutputClaim]:
    """Hold `folder` for `command` while the body writes it; see the module docstring.

    owned: the names inside the folder the command writes (None: the whole folder is its output).
    inputs: files and folders the command reads; --overwrite never removes anything holding them.
    keep: continue the earlier output in place (train --resume) instead of refusing it.
    A command that fails leaves no trace it would not have left anyway: a folder it created and
    wrote nothing into is removed again, and a refused claim leaves no claim file behind.
    """
    folder = Path(folder)
    _check_is_folder(folder)
    created_folder = not folder.exists()
    created_file = not (folder / RUN_FILE).exists()
    handle = _lock(folder)
    host = socket.gethostname()
    claimed, outcome = False, "failed"
    try:
        previous = _read_claim(handle)
        _take_over_stale_claim(folder, previous, host)
        removals = plan_output(folder, command, owned, inputs, overwrite, keep, previous, keep_hint)
        try:
            _write_claim(
                handle,
                {"command": command, "pid": os.getpid(), "host": host, "started": time.time(), "state": "running"},
            )
        except OSError as error:
            raise OutputError(f"--out {folder} cannot be written ({error.strerror}); {os_error_fix(error)}") from error
        claimed = True
        _clean_and_note_interrupted_writes(folder, owned)
        yield OutputClaim(folder, removals)
        outcome = "finished"
    finally:
        with contextlib.suppress(OSError, ValueError):
            _end_claim(folder, handle, outcome, claimed, created_folder, created_file)
        handle.close()  # releases the lock


def _take_over_stale_claim(folder: Path, previous: dict | None, host: str) -> None:
    """Refuse a claim still marked running on another host (not checkable from here); take over, with
    a note, one left running by a process of this host that holds no lock any more."""
    if previous is None or previous.get("state", "running") != "running":
        return
    if previous.get("host", host) != host:
        raise OutputError(
            f"--out {folder} is claimed by {_describe(previous)}, another machine, which "
            f"cannot be checked from here; if that run has stopped, delete {folder / RUN_FILE}"
        )
    console.print(
        f"note: {folder} was left claimed by {_describe(previous)}, which is no longer running; taking it over",
        markup=False,
    )


def _clean_and_note_interrupted_writes(folder: Path, owned: tuple[str, ...] | None) -> None:
    leftovers = clean_interrupted_writes(folder, owned)
    if leftovers:
        names = ", ".join(str(p.relative_to(folder)) for p in leftovers[:5])
        console.print(
            f"note: removed {len(leftovers)} temporary file(s) an interrupted write left in {folder}: {names}",
            markup=False,
        )


def _end_claim(folder: Path, handle, outcome: str, claimed: bool, created_folder: bool, created_file: bool) -> None:
    """A failed command that created the folder and wrote nothing, or was refused before claiming a
    claim file it created, leaves no trace; otherwise the claim records how the command ended."""
    only_the_claim = [p.name for p in folder.iterdir()] == [RUN_FILE]
    if outcome == "failed" and ((created_folder and only_the_claim) or (created_file and not claimed)):
        (folder / RUN_FILE).unlink()  # still locked: no other claim can be using this file
        if created_folder:
            folder.rmdir()
    elif claimed:
        _write_claim(handle, {**(_read_claim(handle) or {}), "state": outcome, "ended": time.time()})
