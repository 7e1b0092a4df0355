"""``python -m mpi_lidar.cli``: the command line, as the ``mpi-lidar`` script runs it."""

from __future__ import annotations

from mpi_lidar.cli import main

main()
