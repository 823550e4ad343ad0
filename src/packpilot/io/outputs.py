"""Output paths checked before a run starts: a missing directory, a directory given as a file,
read-only media or a wrong suffix is found in a second, not after a 100 s simulation."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence
from pathlib import Path

from packpilot.errors import InputError


def check_output(path: Path, option: str, suffixes: Sequence[str] = ()) -> Path:
    """Refuse an output path that cannot be written; ``option`` names the flag in the error.

    The directory is probed by creating (and removing) a temporary file in it: permission
    bits say nothing on read-only media or to root, a real create does."""
    where = f"{option} {path}"
    if suffixes and path.suffix.lower() not in suffixes:
        raise InputError(f"{where}: must end in {' or '.join(suffixes)}")
    if path.is_dir():
        raise InputError(f"{where}: is a directory")
    parent = path.parent
    if not parent.is_dir():
        raise InputError(f"{where}: directory {parent} does not exist")
    if path.exists() and not os.access(path, os.W_OK):
        raise InputError(f"{where}: file is not writable")
    _probe(parent, where)
    return path


def _probe(directory: Path, where: str) -> None:
    try:
        fd, name = tempfile.mkstemp(prefix=".packpilot-probe-", dir=directory)
    except OSError as err:
        raise InputError(f"{where}: cannot write in {directory} ({err.strerror})") from None
    os.close(fd)
    os.unlink(name)


__all__ = ["check_output"]
