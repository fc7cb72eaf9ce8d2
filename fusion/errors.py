"""The exception types fusion raises on purpose.

Policy
------
* :class:`skygen.errors.ConfigError` (re-exported here) — a training config key or
  value is wrong (unknown key, wrong type, out of range, inconsistent keys). Raised
  before any work starts; the message names the dotted key.
* :class:`skygen.errors.DatasetError` (re-exported) — the data on disk is unusable:
  not a skygen dataset, an unsupported schema version (skygen's reader raises it), an
  empty split, too few frames to fit K clusters.
* :class:`CheckpointError` — a checkpoint is unreadable, not a fusion checkpoint, or
  does not match what it is used with (another K, another model or branch set).
* :class:`RunFolderError` — a run folder holds a finished run (use ``--force``) or an
  unfinished one (use ``--resume`` or ``--force``).

All derive from :class:`skygen.errors.SkygenError`; ``fusion``'s command line catches
that base class, prints one line and exits with status 2. Anything else is a bug.
"""

from skygen.errors import ConfigError, DatasetError, SkygenError

__all__ = ["FusionError", "CheckpointError", "RunFolderError", "ConfigError", "DatasetError", "SkygenError"]


class FusionError(SkygenError):
    """Base class of the errors specific to fusion."""


class CheckpointError(FusionError):
    """A checkpoint is unreadable or does not match the model, K or data it is used with."""


class RunFolderError(FusionError):
    """A run folder cannot be used as asked (finished run without --force, ...)."""
