"""``corrected.zarr``: the data product of a corrected scan (corrected depth, flags, bias map), readable by xarray."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import zarr
from numpy.typing import NDArray

from mpi_lidar.correction.correct import Correction
from mpi_lidar.correction.options import CORRECTED_SCHEMA, MODEL_FLAGS, CorrectionOptions, Estimate, Flag
from mpi_lidar.scans.scan import Scan
from mpi_lidar.scans.store import consolidate, store_fingerprints, write_described_arrays
from mpi_lidar.storage.variables import CORRECTED, Store, attributes

if TYPE_CHECKING:
    from zarr.core.common import JSON

CF_CONVENTIONS = "CF-1.10"  # the group's attributes and variables follow these conventions


def write_corrected_store(path: Path, scan: Scan, correction: Correction, identity: dict[str, str],
                          options: CorrectionOptions, outputs: str = "full") -> None:
    """``corrected.zarr``: the corrected depth, the flags and the bias map, readable by ``xarray.open_zarr``.

    Like a scan store: the scan grid's coordinates (``azimuth_rad``/``elevation_rad``, else the pixel indices
    ``y``/``x``), ``units`` and ``long_name`` on every array, CF ``flag_values``/``flag_meanings`` on ``flags``,
    fingerprints of every array, then consolidated metadata. Its arrays are declared in
    :data:`mpi_lidar.storage.variables.CORRECTED`. ``identity`` (the scan's, model's and options'
    hashes) and ``outputs`` (the output level of the scan's outputs) are recorded in the group's attributes.
    """
    group = zarr.open_group(store=str(path), mode="w-")
    written: tuple[tuple[str, NDArray | None], ...] = (
        ("corrected_depth", correction.depth), ("flags", correction.flags),
        ("measured_depth", correction.measured_depth), ("unwrap_confidence", correction.unwrap_confidence),
        ("estimate", correction.estimate), ("depth_uncertainty", correction.uncertainty_m),
        ("multipath_bias_m", correction.multipath_bias_m),
        *(() if (second := correction.second_returns) is None else
          (("second_return_depth", second.depth_m), ("second_return_share", second.share))),
        ("azimuth_rad", scan.azimuth_rad), ("elevation_rad", scan.elevation_rad))
    arrays = {name: (np.asarray(values), CORRECTED[name].dims) for name, values in written if values is not None}
    # CF flag attributes; valid_range bounds the codes (a plot's discrete levels: docs/reference/stores.md).
    flags: dict[str, JSON] = {"flag_values": [int(f) for f in Flag],
                              "flag_meanings": " ".join(f.name.lower() for f in Flag),
                              "valid_range": [0, len(Flag) - 1]}
    estimates: dict[str, JSON] = {"flag_values": [int(e) for e in Estimate],
                                  "flag_meanings": " ".join(e.name.lower() for e in Estimate),
                                  "valid_range": [0, len(Estimate) - 1]}
    write_described_arrays(group, arrays, scan.shape, metadata=attributes(Store.CORRECTED),
                           attributes={"flags": flags, "estimate": estimates})
    # One metadata write: group.attrs.update would rewrite the group's metadata once per key.
    group.update_attributes({"Conventions": CF_CONVENTIONS, "schema": CORRECTED_SCHEMA, "scan_name": scan.name,
                             **identity,
                             "options": options.model_dump(), "flag_codes": {f.name.lower(): int(f) for f in Flag},
                             "counts": correction.counts(), "frequencies_hz": list(scan.frequencies_hz),
                             **({} if correction.calibration is None else {"footprint": footprint_record(correction)}),
                             "outputs": str(outputs), "chunk_sha256": store_fingerprints(group)})
    consolidate(path)


def footprint_record(correction: Correction) -> dict[str, object]:
    """The scan's own footprint estimate, and the pixels it decided: corrected with it, or left as measured."""
    counts = correction.counts()
    estimate = correction.calibration
    if estimate is None:
        raise ValueError("the correction measured no footprint of its own")
    return {"mode": "auto", **estimate.to_dict(),
            "pixels_corrected_with_it": sum(counts[flag.name.lower()] for flag in MODEL_FLAGS)
            if estimate.significant else 0,
            "pixels_left_uncalibrated": counts["uncalibrated"]}
