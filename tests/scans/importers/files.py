"""Files other tools write, for the importer tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr

from tests.scan_factory import two_path_scan

FREQS = two_path_scan("f").frequencies_hz


def save_npz(path: Path, name: str = "frame", seed: int = 0) -> Path:
    scan = two_path_scan(name, height=6, width=5, seed=seed)
    np.savez(path, depth=scan.depth, amplitude=scan.amplitude, azimuth_rad=scan.azimuth_rad,
             elevation_rad=scan.elevation_rad, frequencies_hz=np.asarray(FREQS))
    return path


def tool_dataset(scan) -> xr.Dataset:
    """A scan as another tool might write it: its own names, range in mm, angles in degrees, MHz."""
    dims = ("band", "row", "col")
    return xr.Dataset(
        {"range_mm": (dims, 1e3 * scan.depth.astype(np.float64), {"units": "mm"}),
         "intensity": (dims, scan.amplitude),
         "az": (("col",), np.degrees(scan.azimuth_rad), {"units": "degrees"}),
         "el": (("row",), np.degrees(scan.elevation_rad), {"units": "degree"}),
         "timestamp": ((), 1.7e9, {"units": "seconds since 1970-01-01"})},
        coords={"band_mhz": (("band",), np.asarray(FREQS) / 1e6, {"units": "MHz"})},
    )


MAPPING = {"depth": "range_mm", "amplitude": "intensity", "azimuth_rad": "az", "elevation_rad": "el",
           "frequencies_hz": "band_mhz"}
