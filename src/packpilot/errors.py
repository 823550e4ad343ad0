"""Errors that carry a message fit for a user: they name the file, field or row at fault."""

from __future__ import annotations


class PackPilotError(Exception):
    """Base class; the CLI prints ``str(err)`` on one line and exits with code 2."""


class ConfigError(PackPilotError):
    """A configuration file or value is invalid."""


class InputError(PackPilotError):
    """A data file (profile, log, CAN frame) is invalid."""
