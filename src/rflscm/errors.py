"""User-facing errors.

Everything a user can get wrong (a file, a table, a config key, a CLI option)
raises a subclass of :class:`RflscmError` deep inside the library.  ``rflscm.cli``
catches it once, prints the message on one line and exits with code 2.  Any
other exception is a bug and keeps its traceback.
"""

from __future__ import annotations


class RflscmError(Exception):
    """Base class of all user mistakes (exit code 2 in the CLI)."""


class ConfigError(RflscmError):
    """A configuration value or YAML key is invalid."""


class DataError(RflscmError):
    """A scenario file, table or point cloud is missing or malformed."""


class CheckpointError(RflscmError):
    """A checkpoint cannot be loaded or does not belong to the scenario."""


class UnsupportedError(RflscmError):
    """A model cannot answer this request (e.g. WNOMP asked about a grid it never saw, the oracle about a
    pair the simulation did not trace).  Re-exported by :mod:`rflscm.models`."""
