"""mpi-lidar: multipath-interference suppression for AMCW coaxial scanning LiDAR."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("mpi-lidar")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"
