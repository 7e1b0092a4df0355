"""mpi-lidar: multipath-interference suppression for AMCW coaxial scanning LiDAR.

The Python API (README, "Python API"; docs/reference/python-api.md): ``mpi_lidar.load_model``,
``read_scan``, ``correct_scan``, ``correct_archive``, ``write_point_cloud`` and the others in ``__all__``.
Each is imported on first access (PEP 562), so ``import mpi_lidar`` stays light (the command line's
``--help`` imports it).
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

from mpi_lidar.lazy import lazy_exports

try:
    __version__ = version("mpi-lidar")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"

# name -> the module that defines it (imported when the name is first used)
_EXPORTS = {
    "Config": "mpi_lidar.config",
    "Scan": "mpi_lidar.scans.scan",
    "read_scan": "mpi_lidar.scans.store",
    "write_scan": "mpi_lidar.scans.store",
    "load_scan_file": "mpi_lidar.scans.importers",
    "POINT_CLOUD_FORMATS": "mpi_lidar.scans.pointcloud",
    "correction_fields": "mpi_lidar.scans.pointcloud",
    "point_cloud_fields": "mpi_lidar.reporting.point_cloud_files",
    "write_point_cloud": "mpi_lidar.scans.pointcloud",
    "simulate_rows": "mpi_lidar.simulation.dataset",
    "load_model": "mpi_lidar.learning.model",
    "train_arrays": "mpi_lidar.learning.train",
    "train_and_save": "mpi_lidar.learning.train",
    "bayes_limit": "mpi_lidar.learning.limits",
    "posterior_estimates": "mpi_lidar.learning.limits",
    "CorrectionOptions": "mpi_lidar.correction",
    "correct_scan": "mpi_lidar.correction",
    "correct_archive": "mpi_lidar.workflows.correct_archive",
    "generate": "mpi_lidar.workflows.generate",
    "verify_store": "mpi_lidar.workflows.verify",
}

__all__ = [  # noqa: RUF022 (grouped as in _EXPORTS)
    "__version__", "Config", "Scan", "read_scan", "write_scan", "load_scan_file", "POINT_CLOUD_FORMATS",
    "correction_fields", "point_cloud_fields", "write_point_cloud", "simulate_rows", "load_model", "train_arrays",
    "train_and_save", "bayes_limit", "posterior_estimates", "CorrectionOptions", "correct_scan", "correct_archive",
    "generate", "verify_store",
]

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, __all__)
