"""The exception types the CLI turns into a single error line, and the exit codes."""

from __future__ import annotations

EXIT_USER_ERROR = 2  # the exit code of a user error, for the command line and python -m flows.deploy
EXIT_FAILURE = 1  # something failed that is not the input's fault (a scan of a batch, a damaged store, a bug)


class MpiLidarError(Exception):
    """A user-facing error: the message says what was wrong, where, and what to do."""


class ConfigError(MpiLidarError):
    """A configuration file or value that cannot be used."""


class StoreError(MpiLidarError):
    """A dataset or scan store that is missing, foreign, truncated or from another configuration."""
