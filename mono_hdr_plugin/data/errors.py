"""Errors raised for bad user data: each message names the file or argument and the fix."""

import errno
import os


class DatasetError(ValueError):
    """A dataset file or argument that cannot be used as it is."""


class MissingFileError(DatasetError, FileNotFoundError):
    """A file the dataset layout needs is not there."""


def missing(path, fix: str) -> MissingFileError:
    """The error for a missing file, with what to do about it."""
    return MissingFileError(f"{path}: file not found; {fix}")


# What to do about a file-system error, by errno: the one table every one-line message uses.
_FIXES: dict[int | None, str] = {  # OSError.errno is None when the OS gave no code
    errno.ENOENT: "check the path",
    errno.ENOTDIR: "a part of the path is a file, not a folder: fix the path",
    errno.EISDIR: "it is a folder where a file is expected: pass the file",
    errno.EACCES: "fix its permissions or choose another location",
    errno.EPERM: "fix its permissions or choose another location",
    errno.EROFS: "the file system is read-only: choose a location on a writable disk",
    errno.ENOSPC: "the disk is full: free some space or choose a location on another disk",
    errno.EDQUOT: "the disk quota is used up: free some space or choose a location on another disk",
    errno.ENAMETOOLONG: "shorten the path",
    errno.EEXIST: "a file of that name is in the way of a folder: move or remove it",
    errno.EIO: "the disk reported an input/output error: check it",
}
# Errors third-party writers (OpenEXR, Mitsuba, torch) report as text rather than as OSError.
_RECOGNISED = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EIO)


def os_error_fix(error: OSError) -> str:
    return _FIXES.get(error.errno, "check the path and the disk")


def os_error_line(error: OSError) -> str:
    """One line: the path(s), what went wrong and what to do about it."""
    reason = error.strerror or str(error)
    paths = " -> ".join(str(p) for p in (error.filename, error.filename2) if p is not None)
    return f"{paths}: {reason}; {os_error_fix(error)}" if paths else f"{reason}; {os_error_fix(error)}"


def as_os_error(error: BaseException, path) -> OSError | None:
    """The OSError a library's exception stands for, when its message carries a file-system error
    text (OpenEXR: 'No space left on device'), else None."""
    if isinstance(error, OSError):
        return error
    text = str(error)
    for code in _RECOGNISED:
        if os.strerror(code) in text:
            return OSError(code, os.strerror(code), str(path))
    return None
