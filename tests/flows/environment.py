"""The Prefect environment of the flow tests, set on import: conftest imports this before anything imports Prefect.

Prefect reads its settings from the environment when it is first imported, and Dask worker processes inherit
the environment, so both see a throw-away ``PREFECT_HOME`` (never the user's ``~/.prefect``, profiles or
server), no analytics, a generous server start-up timeout, and quiet logs.
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile

PREFECT_HOME = tempfile.mkdtemp(prefix="mpi-lidar-prefect-home-")
atexit.register(shutil.rmtree, PREFECT_HOME, ignore_errors=True)  # also after a collect-only run
TEST_ENVIRONMENT = {
    "PREFECT_HOME": PREFECT_HOME,
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "180",
    "PREFECT_LOGGING_LEVEL": "WARNING",
    "PREFECT_LOGGING_TO_API_ENABLED": "false",
    "DASK_LOGGING__DISTRIBUTED": "error",
}
_SAVED = {name: os.environ.get(name) for name in [*TEST_ENVIRONMENT, "PREFECT_API_URL"]}

os.environ.update(TEST_ENVIRONMENT)
os.environ.pop("PREFECT_API_URL", None)  # the session starts its own server (conftest.prefect_api)


def restore() -> None:
    """Put the environment back as it was before the tests."""
    for name, value in _SAVED.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
