"""Errors that carry a message fit for a user: they name the file, field or row at fault."""

from __future__ import annotations

from pathlib import Path


class PackPilotError(Exception):
    """Base class; the CLI prints ``str(err)`` on one line and exits with code 2."""


class ConfigError(PackPilotError):
    """A configuration file or value is invalid."""


class InputError(PackPilotError):
    """A data file (profile, log, CAN frame) is invalid."""


def read_text(path: Path, what: str) -> str:
    """The whole of a UTF-8 text file, or an ``InputError`` naming the file and ``what`` it is.

    One place for the three ways a user hands over the wrong thing (missing, a directory,
    binary), so every data file fails with the same one-line message instead of a traceback.
    """
    if not path.exists():
        raise InputError(f"{path}: {what} file not found")
    if not path.is_file():
        raise InputError(f"{path}: {what} is not a file")
    try:
        return path.read_text(encoding="utf-8-sig")  # a leading BOM (Excel's CSV) is dropped
    except UnicodeDecodeError:
        raise InputError(f"{path}: {what} is not a UTF-8 text file") from None
