"""Prefect flows around :mod:`mpi_lidar.workflows`; run from the repository root (``python -m flows.deploy``).

Prefect's server reports anonymous usage to a public endpoint; on an offline cluster that only prints an
error, so it is off unless the environment says otherwise (set before any flow module imports Prefect).
"""

from __future__ import annotations

import os

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
