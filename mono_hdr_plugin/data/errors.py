"""Errors raised for bad user data: each message names the file or argument and the fix."""


class DatasetError(ValueError):
    """A dataset file or argument that cannot be used as it is."""


class MissingFileError(DatasetError, FileNotFoundError):
    """A file the dataset layout needs is not there."""


def missing(path, fix: str) -> MissingFileError:
    """The error for a missing file, with what to do about it."""
    return MissingFileError(f"{path}: file not found; {fix}")
