"""The exception types the CLI turns into a single error line, and the exit codes.

Each also derives from the built-in exception a caller would catch for the same trouble, so code that knows
nothing of this package still handles it: a store that cannot be read is an :class:`OSError`, a configuration
that cannot be used a :class:`ValueError`. Every ``except OSError`` / ``except ValueError`` of the package
around a call that raises these either re-raises them first or wants them.
"""

from __future__ import annotations

EXIT_USER_ERROR = 2  # the exit code of a user error, for the command line and python -m flows.deploy
EXIT_FAILURE = 1  # something failed that is not the input's fault (a scan of a batch, a damaged store, a bug)


class MpiLidarError(Exception):
    """A user-facing error: the message says what was wrong, where, and what to do."""


class ConfigError(MpiLidarError, ValueError):
    """A configuration file or value that cannot be used."""


class StoreError(MpiLidarError, OSError):
    """A dataset or scan store that is missing, foreign, truncated or from another configuration."""
