"""Gates: which valid pixels need correction, so that correction does no harm where a scene has no multipath."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.options import AUTO, CorrectionOptions
from mpi_lidar.correction.validity import quadrature_noise_v2
from mpi_lidar.scans import geometry
from mpi_lidar.scans.scan import Scan
from mpi_lidar.threads import on_cores

if TYPE_CHECKING:
    from mpi_lidar.correction.calibration import FootprintEstimate, PlaneModelInputs


class Gate(ABC):
    """Decides which valid pixels need correction.

    Contract: ``needs_correction(raw, frequencies_hz, sensor)`` takes the raw measurements (n, 2F) of valid
    pixels and returns a bool (n,): True where the model should correct. It must be much cheaper than
    inference, since its purpose is to skip work. A gate that looks at the whole scan first overrides
    ``scan_candidates``: a bool (H*W,) of the pixels that may need correction (the others get
    NO_MULTIPATH), or None where it cannot tell; ``uses_geometry`` says whether it wants the geometry.
    """

    name: str
    uses_geometry = False

    def scan_candidates(self, scan: Scan, valid_depth: NDArray) -> NDArray | None:
        """Bool (H*W,) of pixels that may need correction, from the whole scan; None: every pixel may."""
        return None

    @abstractmethod
    def needs_correction(self, raw: NDArray, frequencies_hz: tuple[float, ...], sensor: SensorConfig) -> NDArray:
        """Bool (n,)."""


class CorrectAll(Gate):
    """Every valid pixel is corrected (the paper's pixel-wise correction)."""

    name = "all"

    def needs_correction(self, raw: NDArray, frequencies_hz: tuple[float, ...], sensor: SensorConfig) -> NDArray:
        return np.ones(raw.shape[0], dtype=bool)


class ConsistencyGate(Gate):
    """Corrects pixels whose per-frequency depths disagree by more than their predicted noise allows.

    A pixel with no multipath has the same depth at every frequency up to noise; chi^2 of the depths around
    their inverse-variance mean, with each depth's noise predicted by the moment model at the measured
    amplitude (thermal, TIA and shot noise), follows chi^2(F-1).
    Pixels below the (1 - p) quantile are skipped. At Table I noise and d_AB <= 15 cm the multipath offset
    is almost the same at every frequency, so this test misses most multipath: it is cheap, not sufficient.
    """

    name = "consistency"

    def __init__(self, p_value: float):
        self.p_value = p_value

    def needs_correction(self, raw: NDArray, frequencies_hz: tuple[float, ...], sensor: SensorConfig) -> NDArray:
        f = len(frequencies_hz)
        freqs = np.asarray(frequencies_hz)
        depth = raw[:, :f].astype(np.float64)
        amplitude = np.maximum(raw[:, f:].astype(np.float64), 1e-12)
        metres_per_rad = sensor.speed_of_light_m_per_s / (4 * np.pi * freqs)
        sigma = quadrature_noise_v2(sensor, tuple(frequencies_hz), amplitude) / amplitude * metres_per_rad[None, :]
        weight = sigma**-2
        mean = (weight * depth).sum(1, keepdims=True) / weight.sum(1, keepdims=True)
        chi2 = (weight * (depth - mean) ** 2).sum(1)
        from scipy import stats  # 1-2 s of imports that only this gate needs

        return chi2 > stats.chi2.ppf(1 - self.p_value, df=f - 1)


class GeometryGate(Gate):
    """Corrects only pixels where the scan's geometry allows multipath (:func:`geometry.multipath_potential`).

    A pixel is a candidate where the expected multipath bias of its facing surfaces (white partner, small
    phase) reaches ``min_bias_m`` [m]; flat walls, convex objects and open sky have none. The potential is
    computed from the raw highest-frequency depth of the valid pixels. Scans without geometry (no rays or
    scan grid) get None: every valid pixel is corrected, pixel-wise.

    With ``footprint_area_m2`` = "auto" the scan measures its own footprint
    (:func:`mpi_lidar.correction.calibration.estimate_footprint`, kept in ``calibration_``). Where the
    estimate is not significant, the potential is that of no multipath and ``uncalibrated_`` marks the
    pixels whose bias could still reach ``min_bias_m`` at the estimate's upper bound: they are left as measured.
    """

    name = "geometry"
    uses_geometry = True

    def __init__(self, min_bias_m: float, block_m: float, partner_range_m: float, footprint_area_m2: float | str,
                 sensor: SensorConfig | None = None, band_pixels: int = geometry.BAND_PIXELS):
        self.min_bias_m = min_bias_m
        self.block_m = block_m
        self.partner_range_m = partner_range_m
        self.footprint_area_m2 = footprint_area_m2
        self.sensor = sensor or SensorConfig()
        self.band_pixels = band_pixels
        self.potential_: geometry.BlockPotential | None = None
        self.bias_m_: NDArray[np.float32] | None = None
        self.calibration_: FootprintEstimate | None = None
        self.uncalibrated_: NDArray | None = None
        self.blocks_: geometry.FacingBlocks | None = None
        self.footprint_m2_ = 0.0
        self._measured_albedo: NDArray | None = None

    def potential(self, scan: Scan, valid_depth: NDArray) -> geometry.BlockPotential | None:
        """The scan's potential per block (pixels interpolate it), or None for a scan without geometry.

        Keeps the blocks (``blocks_``) and the footprint the potential is for (``footprint_m2_``, 0 where the
        scan's own estimate is not significant) for :meth:`model_inputs`.
        """
        rays = scan.ray_rows()
        if rays is None:
            return None
        blocks = geometry.facing_blocks(valid_depth.reshape(scan.shape), rays, block_m=self.block_m,
                                        max_range_m=self.partner_range_m, band_pixels=self.band_pixels)
        self.blocks_, self._measured_albedo = blocks, None
        if self.footprint_area_m2 != AUTO:
            self.footprint_m2_ = self.footprint_area_m2
            return blocks.block_potential(self.footprint_m2_)
        from mpi_lidar.correction.calibration import estimate_footprint

        estimate = estimate_footprint(scan, blocks, np.isfinite(valid_depth), self.sensor,
                                      measured_albedo=self.measured_albedo(scan))
        self.calibration_ = estimate
        if estimate.significant:
            self.footprint_m2_ = estimate.area_m2
            return blocks.block_potential(estimate.area_m2)
        upper = blocks.block_potential(min(estimate.upper_m2(), 1.0))
        self.uncalibrated_ = self._reaches_min_bias(upper)
        self.footprint_m2_ = 0.0
        return blocks.block_potential(0.0)

    def measured_albedo(self, scan: Scan) -> NDArray[np.float64]:
        """The albedo of every block of :meth:`potential`'s blocks from its amplitude (Hb*Wb,), worked out once."""
        from mpi_lidar.correction.calibration import block_albedo

        if self._measured_albedo is None:
            self._measured_albedo = block_albedo(scan, self.blocks_, self.sensor, self.band_pixels)
        return self._measured_albedo

    def model_inputs(self, scan: Scan) -> PlaneModelInputs | None:
        """A correction model's geometric inputs after :meth:`scan_candidates`, at the footprint the potential is
        for (None for a scan without geometry): per pixel from the partner planes
        (:class:`mpi_lidar.correction.calibration.PlaneModelInputs`), and where a pixel lies on no plane from
        the facing blocks, each partner weighted by its surface's albedo (from the amplitude) over the
        incidence cosine (:meth:`mpi_lidar.scans.geometry.FacingBlocks.equivalent_rho_aba`)."""
        from mpi_lidar.correction.calibration import PlaneCoupling, PlaneModelInputs, partner_albedo, surface_labels

        if self.potential_ is None or self.blocks_ is None:
            return None
        blocks = self.blocks_
        if blocks.pairs.a.size == 0 or self.footprint_m2_ <= 0:
            return PlaneModelInputs(blocks.equivalent_rho_aba(0.0, np.zeros(blocks.usable.size)))
        measured = self.measured_albedo(scan)
        components, labels = surface_labels(blocks)
        fallback = blocks.equivalent_rho_aba(self.footprint_m2_, partner_albedo(blocks, measured, components))
        plane = PlaneCoupling(scan, blocks, components, labels, self.sensor)
        albedo = plane.light_free_albedo(measured, components, self.footprint_m2_)
        return PlaneModelInputs(fallback, plane, albedo, self.footprint_m2_)

    def scan_candidates(self, scan: Scan, valid_depth: NDArray) -> NDArray | None:
        """Also keeps the potential (``potential_``) and the expected bias map (``bias_m_``, float32 (H, W))."""
        self.potential_ = self.potential(scan, valid_depth)
        if self.potential_ is None:
            return None
        self.bias_m_ = np.empty(scan.shape, dtype=np.float32)
        return self._reaches_min_bias(self.potential_, self.bias_m_)

    def _reaches_min_bias(self, potential: geometry.BlockPotential, bias_out: NDArray | None = None
                          ) -> NDArray[np.bool_]:
        """Where the bias reaches ``min_bias_m`` (H*W,), a band of rows at a time; the bias [m] goes into
        ``bias_out`` (H, W) where given."""
        reaches = np.empty(potential.blocks.shape, dtype=bool)

        def band(rows: slice) -> None:
            bias = potential.bias_rows(rows)
            reaches[rows] = bias >= self.min_bias_m
            if bias_out is not None:
                bias_out[rows] = bias

        on_cores(band, potential.blocks.bands(self.band_pixels))
        return reaches.ravel()

    def needs_correction(self, raw: NDArray, frequencies_hz: tuple[float, ...], sensor: SensorConfig) -> NDArray:
        return np.ones(raw.shape[0], dtype=bool)


NO_GEOMETRY_NOTE = "no scan geometry: the geometry gate fell back to pixel-wise correction of every valid pixel"
NO_GEOMETRY_INPUTS_NOTE = ("no scan geometry: the model needs geometric inputs (rho_ABA, d_AB), so every valid "
                           "pixel keeps its raw depth")


def geometry_gate(options: CorrectionOptions, sensor: SensorConfig | None = None) -> GeometryGate:
    return GeometryGate(options.min_multipath_bias_m, options.geometry_block_m, options.partner_range_m,
                        options.footprint_area_m2, sensor, options.tile_pixels)


def make_gate(options: CorrectionOptions, sensor: SensorConfig | None = None) -> Gate:
    gates = {"all": lambda: CorrectAll(), "consistency": lambda: ConsistencyGate(options.consistency_p_value),
             "geometry": lambda: geometry_gate(options, sensor)}
    return gates[options.gate]()
