"""The project's exception types.

Policy
------
* :class:`ConfigError` — a configuration key or value is wrong. Raised before any work
  starts; the message names the dotted key, the value given and what is allowed.
* :class:`DatasetError` — a file or folder on disk is not what it should be (truncated,
  foreign, unknown schema version, checksum mismatch, a different dataset in the output
  folder). The message names the file and says how to recover.
* :class:`FolderInUseError` — an output folder is locked by another running writer
  (:mod:`skygen.lock`); the message names it (what, PID, host, start, command).
* :class:`CatalogError` — a star catalog could not be read or fetched.

All derive from :class:`SkygenError`, which the command-line interface catches
and prints without a traceback (exit code 2). Anything else is a bug.
"""


class SkygenError(Exception):
    """Base class of every error skygen raises on purpose."""


class ConfigError(SkygenError, ValueError):
    """A configuration key or value is invalid."""


class DatasetError(SkygenError, OSError):
    """A dataset, shard or manifest on disk is missing, damaged or incompatible."""


class FolderInUseError(DatasetError):
    """An output folder is being written by another process (see :mod:`skygen.lock`)."""


class CatalogError(SkygenError):
    """A star catalog could not be parsed or fetched."""
