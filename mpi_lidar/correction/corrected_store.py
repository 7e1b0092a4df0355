"""``corrected.zarr``: the data product of a corrected scan (corrected depth, flags, bias map), readable by xarray."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import zarr
from numpy.typing import NDArray

from mpi_lidar.correction.correct import Correction
from mpi_lidar.correction.options import CORRECTED_SCHEMA, MODEL_FLAGS, CorrectionOptions, Estimate, Flag
from mpi_lidar.scans.scan import Scan, grid_rays
from mpi_lidar.scans.store import consolidate, store_fingerprints, write_described_arrays
from mpi_lidar.storage.variables import CORRECTED, Store, attributes

if TYPE_CHECKING:
    from zarr.core.common import JSON

CF_CONVENTIONS = "CF-1.10"  # the group's attributes and variables follow these conventions
# Ray directions within this of the rays of one azimuth per column and one elevation per row are a regular grid
# (a chord of unit vectors, about the angle between them): float32 rays of a grid agree to about 1e-7.
SEPARABLE_TOLERANCE_RAD = 1e-6
RAY_BAND_ROWS = 256  # rows of ray directions compared at a time: a large scan's rays are never copied whole
# Where the scan grid is regular, the pixel axes are named after the angles that label them, so that xarray
# takes azimuth_rad and elevation_rad as dimension coordinates (index, plot axes, .sel).
ANGLE_DIMS = {"y": "elevation_rad", "x": "azimuth_rad"}


def write_corrected_store(path: Path, scan: Scan, correction: Correction, identity: dict[str, str],
                          options: CorrectionOptions, outputs: str = "full") -> None:
    """``corrected.zarr``: the corrected depth, the flags and the bias map, readable by ``xarray.open_zarr``.

    Where the scan grid is regular (:func:`regular_grid`) its maps' dimensions are ``(elevation_rad,
    azimuth_rad)`` and the angles [rad] are their dimension coordinates, so xarray indexes and plots the maps
    against them; otherwise the maps are ``(y, x)``, labelled by a scan's own angles where it has them and by
    the pixel indices ``y``/``x`` where it does not. ``units`` and ``long_name`` on every array, CF
    ``flag_values``/``flag_meanings`` on ``flags`` and ``estimate``, a ``Conventions`` attribute,
    fingerprints of every array, then consolidated metadata. Its arrays are declared in
    :data:`mpi_lidar.storage.variables.CORRECTED`. ``identity`` (the scan's, model's and options'
    hashes) and ``outputs`` (the output level of the scan's outputs) are recorded in the group's attributes.
    """
    group = zarr.open_group(store=str(path), mode="w-", zarr_format=3)
    written: tuple[tuple[str, NDArray | None], ...] = (
        ("corrected_depth", correction.depth), ("flags", correction.flags),
        ("measured_depth", correction.measured_depth), ("unwrap_confidence", correction.unwrap_confidence),
        ("estimate", correction.estimate), ("depth_uncertainty", correction.uncertainty_m),
        ("multipath_bias_m", correction.multipath_bias_m),
        *(() if (second := correction.second_returns) is None else
          (("second_return_depth", second.depth_m), ("second_return_share", second.share),
           ("second_return_uncertainty", second.sigma_m))))
    grid = regular_grid(scan)
    angles = (scan.azimuth_rad, scan.elevation_rad) if grid is None else grid
    dims = ANGLE_DIMS if grid is not None else {}
    arrays = {name: (np.asarray(values), tuple(dims.get(d, d) for d in CORRECTED[name].dims))
              for name, values in (*written, ("azimuth_rad", angles[0]), ("elevation_rad", angles[1]))
              if values is not None}
    # CF flag attributes; valid_range bounds the codes (a plot's discrete levels: docs/reference/stores.md).
    flags: dict[str, JSON] = {"flag_values": [int(f) for f in Flag],
                              "flag_meanings": " ".join(f.name.lower() for f in Flag),
                              "valid_range": [0, len(Flag) - 1]}
    estimates: dict[str, JSON] = {"flag_values": [int(e) for e in Estimate],
                                  "flag_meanings": " ".join(e.name.lower() for e in Estimate),
                                  "valid_range": [0, len(Estimate) - 1]}
    derived: dict[str, JSON] = ({"comment": "derived from the scan's ray_directions"}
                                if grid is not None and scan.azimuth_rad is None else {})
    write_described_arrays(group, arrays, scan.shape, metadata=attributes(Store.CORRECTED),
                           attributes={"flags": flags, "estimate": estimates, "azimuth_rad": derived,
                                       "elevation_rad": derived})
    # One metadata write: group.attrs.update would rewrite the group's metadata once per key.
    group.update_attributes({"Conventions": CF_CONVENTIONS, "schema": CORRECTED_SCHEMA, "scan_name": scan.name,
                             **identity,
                             "options": options.model_dump(), "flag_codes": {f.name.lower(): int(f) for f in Flag},
                             "counts": correction.counts(), "frequencies_hz": list(scan.frequencies_hz),
                             **({} if correction.calibration is None else {"footprint": footprint_record(correction)}),
                             "outputs": str(outputs), "chunk_sha256": store_fingerprints(group)})
    consolidate(path)


def regular_grid(scan: Scan) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """The azimuth (W,) and elevation (H,) [rad] of a regular scan grid, or None where the scan has none.

    Regular: azimuth depends on the column only and elevation on the row only, each strictly monotonic, so that
    they can index the maps' columns and rows. A scan's own ``azimuth_rad``/``elevation_rad`` depend on one axis
    each by construction; ``ray_directions`` qualify where every ray lies within
    :data:`SEPARABLE_TOLERANCE_RAD` of the ray of its column's azimuth and its row's elevation, read from the
    middle row and column.
    """
    grid: tuple[NDArray[np.float64], NDArray[np.float64]] | None
    if scan.azimuth_rad is not None and scan.elevation_rad is not None:
        grid = (np.asarray(scan.azimuth_rad), np.asarray(scan.elevation_rad))
    elif scan.ray_directions is not None:
        grid = _separable_angles(scan.ray_directions)
    else:
        grid = None
    if grid is None or not all(_strictly_monotonic(angles) for angles in grid):
        return None
    return grid


def _separable_angles(rays: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """Azimuth (W,) and elevation (H,) [rad] whose grid rays are ``rays`` (H, W, 3) within the tolerance, or None.

    ``rays`` is read by slices of rows only, so that rays kept in the scan's store are read a band at a time.
    """
    h, w, _ = rays.shape
    row = np.asarray(rays[h // 2:h // 2 + 1], dtype=np.float64)[0]
    column = np.asarray(rays[:, w // 2:w // 2 + 1], dtype=np.float64)[:, 0]
    azimuth = np.arctan2(row[:, 0], row[:, 2])  # scale-free: the rays are unit vectors only within 0.1 %
    elevation = np.arctan2(column[:, 1], np.hypot(column[:, 0], column[:, 2]))
    for top in range(0, h, RAY_BAND_ROWS):
        band = np.asarray(rays[top:top + RAY_BAND_ROWS], dtype=np.float64)
        band = band / np.linalg.norm(band, axis=-1, keepdims=True)  # a new array: the scan's rays stay as they are
        if not np.abs(band - grid_rays(azimuth, elevation[top:top + RAY_BAND_ROWS])).max() <= SEPARABLE_TOLERANCE_RAD:
            return None  # not separable (or a ray not finite)
    return azimuth, elevation


def _strictly_monotonic(angles: NDArray) -> bool:
    steps = np.diff(np.asarray(angles, dtype=np.float64))
    return bool((steps > 0).all() or (steps < 0).all())


def footprint_record(correction: Correction) -> dict[str, object]:
    """The scan's own footprint estimate (and the depth's and the amplitude's estimates it joins, None where not
    both fitted), and the pixels it decided: corrected with it, or left as measured."""
    counts = correction.counts()
    estimate = correction.calibration
    if estimate is None:
        raise ValueError("the correction measured no footprint of its own")
    own = {name: (value if np.isfinite(value) else None)
           for name, value in (("depth_m2", estimate.depth_m2), ("amplitude_m2", estimate.amplitude_m2))}
    return {"mode": "auto", **estimate.to_dict(), **own,
            "pixels_corrected_with_it": sum(counts[flag.name.lower()] for flag in MODEL_FLAGS)
            if estimate.significant else 0,
            "pixels_left_uncalibrated": counts["uncalibrated"]}
