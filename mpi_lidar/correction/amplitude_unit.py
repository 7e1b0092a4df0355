"""A scan's amplitude unit, read from how much its frequencies disagree: the amplitude-unit stage.

The noise model (:class:`mpi_lidar.physics.noise.NoiseModel`) predicts each frequency's depth sd from its
amplitude in V^2. A scanner that reports amplitudes in its own unit, ``A = lambda A_V2``, has its sds predicted at
``A / lambda``. Where the frequencies see one range, the weighted scatter of a pixel's depths about their
inverse-variance mean, chi2 = sum_f (d_f - mean)^2 / sd_f^2, follows chi-square with F - 1 degrees of freedom when
lambda is right; too large a lambda predicts too much noise and chi2 reads small, too small a lambda too little
(the predicted variance, eta^2 (a lambda^2 / A^2 + b lambda / A), grows with lambda). So the unit is the lambda
at which the median chi2 of the scan's pixels equals chi-square's median: no plane, no flat surface, any scene.

Multipath at these frequencies moves every frequency's depth nearly alike (the consistency gate's premise), so
it adds little to chi2, and the median ignores the pixels where it does; the frequencies' fixed depth offsets
are removed first (the median of each one's depth less the highest one's). Only the product of lambda and the
noise scale eta is seen: eta is held at the noise model's.

:func:`read_amplitude_unit` is the stage: the unit the options give, or the scan's own reading
(:class:`UnitReading`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.options import AUTO, CorrectionOptions
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.scans.scan import Scan

# Pixels the unit is read from at most, evenly spaced over the scan: the unit's relative sd is then ~1-1.5 %, below
# the noise model's own error.
SAMPLE_PIXELS = 10_000
# A unit is significant from at least this many pixels (where the median's large-sample sd holds), known to this
# relative sd.
MIN_PIXELS = 50
MAX_RELATIVE_SIGMA = 0.1
# Where the median amplitude would read as this range of V^2 the unit is looked for (wider than any sensor's).
MEDIAN_AMPLITUDE_RANGE_V2 = (1e-7, 1e2)
# The root in log lambda is found to this tolerance: 1e-4 relative, far below the reading's sd.
LOG_SCALE_TOLERANCE = 1e-4
# A unit read within this factor of V^2 is taken as V^2 (:func:`reads_as_v2`): the sensor's noise, which the reading
# takes to be the noise model's, moves it that much (only the product of unit and noise scale is seen), while a unit
# of another scale (counts, mW) differs by orders of magnitude. Searched first, the scans in V^2 cost less.
V2_TOLERANCE = 2.0


@dataclass(frozen=True)
class AmplitudeUnit:
    """A scan's amplitude unit (:func:`measure_amplitude_unit`).

    amplitude_scale : lambda, the scanner's unit per V^2 (NaN where not measured). [units / V^2]
    relative_sigma : Its relative standard deviation (inf where not measured). [1]
    pixels : Pixels it was read from.
    significant : At least ``MIN_PIXELS`` pixels and a relative sd of at most ``MAX_RELATIVE_SIGMA``.
    reason : Why not, where it is not significant.
    """

    amplitude_scale: float
    relative_sigma: float
    pixels: int
    significant: bool
    reason: str = ""


@dataclass(frozen=True)
class UnitReading:
    """The amplitude-unit stage's result (:func:`read_amplitude_unit`).

    units_per_v2 : The scanner's unit per V^2 the amplitudes are divided by (1: V^2). [1 / V^2]
    measured : The scan's own reading where the options said "auto" (None: the options gave the unit).
    known : Whether the unit is known; a scan whose unit is not is left as measured.
    """

    units_per_v2: float
    measured: AmplitudeUnit | None = None

    @property
    def known(self) -> bool:
        return self.measured is None or self.measured.significant


def read_amplitude_unit(scan: Scan, noise: NoiseModel, options: CorrectionOptions) -> UnitReading:
    """The amplitude-unit stage: the unit ``options.amplitude_scale`` gives, or with "auto" the scan's own
    (:func:`measure_amplitude_unit`), a unit within ``V2_TOLERANCE`` of V^2 read as V^2."""
    if options.amplitude_scale != AUTO:
        return UnitReading(float(options.amplitude_scale))
    unit = measure_amplitude_unit(scan, noise, max_depth_spread_m=options.max_depth_spread_m)
    if not unit.significant:
        return UnitReading(float("nan"), unit)
    return UnitReading(1.0 if reads_as_v2(unit) else unit.amplitude_scale, unit)


def measure_amplitude_unit(scan: Scan, noise: NoiseModel, *, max_depth_spread_m: float = 0.3) -> AmplitudeUnit:
    """The amplitude unit of ``scan`` from the chi-square of its frequencies' depths (the module's docstring).

    Reads at most ``SAMPLE_PIXELS`` evenly spaced pixels with finite depths and positive amplitudes whose depths,
    unwrapped where the scan's are wrapped, spread over at most ``max_depth_spread_m`` [m]; ``noise`` is the
    sensor's noise model in V^2 (its noise scale included).
    """
    rows = _sample_rows(scan)
    f = len(scan.frequencies_hz)
    if scan.depth_wrapped and rows.shape[0]:
        # Weights of the sds' shape at one amplitude: the amplitudes' unit is not known yet.
        rows = noise.unwrap(rows, equal_amplitudes=True)[0].astype(np.float64)
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(rows).all(1) & (rows[:, f:] > 0).all(1)
        keep &= rows[:, :f].max(1) - rows[:, :f].min(1) <= max_depth_spread_m
    rows = rows[keep]
    if rows.shape[0] < MIN_PIXELS:
        return AmplitudeUnit(float("nan"), float("inf"), int(rows.shape[0]), False,
                             f"only {rows.shape[0]} pixels with consistent depths, at least {MIN_PIXELS} needed")
    offsets = np.median(rows[:, :f] - rows[:, f - 1:f], axis=0)
    return _solve(rows, offsets, noise)


def _sample_rows(scan: Scan) -> NDArray[np.float64]:
    """Raw rows (n, 2F) of at most ``SAMPLE_PIXELS`` pixels evenly spaced over the scan, in float64."""
    h, w = scan.shape
    pixels = np.unique(np.linspace(0, h * w - 1, min(SAMPLE_PIXELS, h * w)).round().astype(np.intp))
    y, x = np.divmod(pixels, w)
    depth = np.asarray(scan.depth[:, y, x], dtype=np.float64).T
    amplitude = np.asarray(scan.amplitude[:, y, x], dtype=np.float64).T
    return np.hstack([depth, amplitude])


def _median_chi2(rows: NDArray, offsets: NDArray, noise: NoiseModel, log_scale: float) -> float:
    f = len(noise.frequencies_hz)
    scaled = np.hstack([rows[:, :f], rows[:, f:] / np.exp(log_scale)])
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        fused = noise.fuse(scaled, offsets_m=offsets)
    return float(np.median((f - 1) * fused.birge_ratio.astype(np.float64) ** 2))


def _solve(rows: NDArray, offsets: NDArray, noise: NoiseModel) -> AmplitudeUnit:
    """lambda where the median chi2 equals chi-square's median, by Brent's method in log lambda (chi2 falls as
    lambda grows), and its relative sd from the median's."""
    from scipy.optimize import brentq
    from scipy.special import chdtri  # scipy.stats would cost a one-scan correction 0.33 s of imports

    f = len(noise.frequencies_hz)
    target = float(chdtri(f - 1, 0.5))  # chi-square's median: the value its upper tail exceeds half the time
    median_amplitude = float(np.median(rows[:, f:]))
    low, high = (np.log(median_amplitude / bound) for bound in MEDIAN_AMPLITUDE_RANGE_V2[::-1])
    at = {bound: _median_chi2(rows, offsets, noise, bound) for bound in (low, high)}
    n = rows.shape[0]
    if not at[low] >= target >= at[high]:
        return AmplitudeUnit(float("nan"), float("inf"), n, False,
                             "the frequencies' scatter matches no amplitude unit within the searched range")

    def excess(log_scale: float) -> float:
        return _median_chi2(rows, offsets, noise, log_scale) - target

    bracket = (low, high)
    near = np.log(1.0 / V2_TOLERANCE), np.log(V2_TOLERANCE)
    if excess(near[0]) >= 0 >= excess(near[1]):  # within the tolerance of V^2, as most scans are
        bracket = near
    log_scale = float(brentq(excess, *bracket, xtol=LOG_SCALE_TOLERANCE))
    relative_sigma = _relative_sigma(rows, offsets, noise, log_scale, target, n)
    significant = relative_sigma <= MAX_RELATIVE_SIGMA
    reason = "" if significant else (f"the unit is known only to {relative_sigma:.2g} (relative sigma), more than "
                                     f"{MAX_RELATIVE_SIGMA:g}: too few pixels whose frequencies agree")
    return AmplitudeUnit(float(np.exp(log_scale)), relative_sigma, n, significant, reason)


def _relative_sigma(rows: NDArray, offsets: NDArray, noise: NoiseModel, log_scale: float, target: float,
                    n: int) -> float:
    """The relative sd of lambda: the sample median's sd, 1 / (2 p(m) sqrt(n)) with p chi-square's density at its
    median m, carried through the slope of log median chi2 against log lambda."""
    f = len(noise.frequencies_hz)
    median_sd = 1.0 / (2.0 * _chi_square_density(target, f - 1) * np.sqrt(n))
    step = 0.05
    slope = (np.log(_median_chi2(rows, offsets, noise, log_scale + step))
             - np.log(_median_chi2(rows, offsets, noise, log_scale - step))) / (2 * step)
    if not np.isfinite(slope) or slope >= 0:
        return float("inf")
    return float((median_sd / target) / abs(slope))


def _chi_square_density(x: float, dof: int) -> float:
    """Chi-square's probability density with ``dof`` degrees of freedom at ``x`` > 0."""
    from scipy.special import gammaln

    half = dof / 2.0
    return float(np.exp((half - 1.0) * np.log(x) - x / 2.0 - half * np.log(2.0) - gammaln(half)))


def reads_as_v2(unit: AmplitudeUnit) -> bool:
    """Whether a measured amplitude unit is taken as V^2 (within ``V2_TOLERANCE`` of it)."""
    return 1.0 / V2_TOLERANCE <= unit.amplitude_scale <= V2_TOLERANCE
