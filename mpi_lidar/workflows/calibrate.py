"""``mpi-lidar calibrate``: measure a sensor's receiver footprint on its own scans and write a sensor profile."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.footprint import NOTHING_MEASURED, FootprintEstimate, estimate_footprint, pool_estimates
from mpi_lidar.correction.options import CorrectionOptions
from mpi_lidar.correction.profile import SensorProfile, write_profile
from mpi_lidar.correction.scene import scene_blocks
from mpi_lidar.correction.validity import usable_depth_of, validity_flags
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.scans.scan import Scan
from mpi_lidar.scans.store import read_scan
from mpi_lidar.workflows.correct_archive import expand_archive


@dataclass(frozen=True)
class ScanEstimate:
    """One scan's footprint estimate and where it came from."""

    source: str
    estimate: FootprintEstimate


def scan_footprint(scan: Scan, options: CorrectionOptions, sensor: SensorConfig, use_reference: bool = True
                   ) -> FootprintEstimate:
    """The footprint one scan measures: against its reference depth where it has one (and ``use_reference``),
    else against its own surfaces. A scan without geometry measures nothing.

    The stages of correction (:func:`mpi_lidar.correction.correct_scan`) up to the footprint: validity over the
    whole scan (no model, so no model range), then the scene's blocks (:func:`scene_blocks`)."""
    if scan.ray_rows() is None:
        return NOTHING_MEASURED
    raw = scan.raw_pixels()
    usable_depth = usable_depth_of(raw, validity_flags(raw, scan.frequencies_hz, options, sensor))
    valid = np.isfinite(usable_depth)
    blocks = scene_blocks(scan, usable_depth, options)
    assert blocks is not None  # the scan has rays
    reference = use_reference and scan.reference_depth is not None
    if reference:
        valid &= np.isfinite(np.asarray(scan.reference_depth, dtype=np.float64)).ravel()
    return estimate_footprint(scan, blocks, valid, sensor, reference=reference)


def calibrate_scans(inputs: list[str], out: str | Path, options: CorrectionOptions | None = None,
                    use_reference: bool = True, on_scan: Callable[[ScanEstimate], None] | None = None
                    ) -> tuple[SensorProfile, list[ScanEstimate]]:
    """Pool the footprint of every scan of ``inputs`` (stores, directories, globs) and write the profile to ``out``.

    A pooled estimate that is not significant writes nothing: the scans hold too little facing geometry.
    """
    options = options or CorrectionOptions()
    if Path(out).exists():
        raise MpiLidarError(f"sensor profile {out} already exists; choose another --out or remove it")
    sources = expand_archive(inputs)
    results = []
    for source in sources:
        result = ScanEstimate(source, scan_footprint(read_scan(source), options, SensorConfig(), use_reference))
        results.append(result)
        if on_scan:
            on_scan(result)
    pooled = pool_estimates([r.estimate for r in results])
    if not pooled.significant:
        raise MpiLidarError(
            f"the {len(sources)} scans give no significant footprint ({_describe(pooled)}); calibrate on scans "
            "with corners or other surfaces facing each other, or give --footprint-area-m2 to correct")
    thresholds = {"saturation_amplitude_v2": options.saturation_amplitude_v2,
                  "min_amplitude_sigmas": options.min_amplitude_sigmas}
    profile = SensorProfile.from_estimate(pooled, sources, **thresholds)
    write_profile(profile, out)
    return profile, results


def _describe(estimate: FootprintEstimate) -> str:
    if not np.isfinite(estimate.area_m2):
        return "no facing surfaces found"
    return f"{estimate.area_m2:.4g} +- {estimate.sigma_m2:.2g} m^2 from {estimate.pixels:,} pixels"


def describe(estimate: FootprintEstimate) -> str:
    """One line of a scan's or a pool's estimate, for the command line."""
    verdict = "significant" if estimate.significant else "not significant"
    return f"{_describe(estimate)} ({estimate.method}, {verdict})"
