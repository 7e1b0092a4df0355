"""Prefect flows around :mod:`mpi_lidar.workflows`; run from the repository root: ``python -m flows FLOW ...``
runs one in this process (:mod:`flows.__main__`), ``python -m flows.deploy`` serves the deployments.

Prefect reports anonymous usage to a public endpoint, from its server (analytics) and from the client (SDK
telemetry); on an offline cluster that only prints errors, so both are off unless the environment says
otherwise (set before any flow module imports Prefect; Dask workers and the temporary server inherit it).
"""

from __future__ import annotations

import os

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")
