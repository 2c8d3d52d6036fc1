"""Errors that reach the user as one line (DESIGN.md section 6, convention 2).

Everything the user can get wrong (a file, a topic, a config key) raises a subclass of
`CvslamError`; `cli.main` prints its message on one line and exits with status 1. Any other
exception is a bug and keeps its traceback.
"""

from __future__ import annotations


class CvslamError(Exception):
    """A problem with the user's input, reported as one line, exit status 1."""


class ConfigError(CvslamError):
    """A config file or --set override is invalid (names the file and key path)."""


class LogError(CvslamError):
    """A log (MCAP) cannot be read or holds data that cannot be used (names file and topic)."""


class CalibrationError(CvslamError):
    """Camera calibration is missing or inconsistent (names the source)."""


class DatasetError(CvslamError):
    """A dataset folder given to an importer is missing files or malformed."""
