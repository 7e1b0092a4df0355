"""The validity stage: one range from the wrapped depths, and which pixels can be trusted at all (finite, above
the noise floor, unsaturated, frequencies consistent), in one pass over the scan's tiles (:func:`check_validity`).

The same pass keeps what later stages need from the raw measurements, so that they are read only once more after
the scene geometry: a sample of the frequencies' relative depths for their offsets (:class:`OffsetSample`), the
unwrapped depths of the pixels that took a wrap count, and a pixel-wise gate's decision.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.gates import Gate
from mpi_lidar.correction.options import INVALID_FLAGS, CorrectionOptions, Flag
from mpi_lidar.correction.tiles import PARALLEL_MIN_ROWS, raw_tiles, unwrapped_scan
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.physics.window import window_corrections_m
from mpi_lidar.scans.scan import NOISE_DEVIATIONS, Scan
from mpi_lidar.threads import on_cores_by_rows

# Pixels whose depth the scene geometry and the model cannot use: the invalid ones, and those of an unknown range.
UNUSABLE_FLAGS = (*INVALID_FLAGS, Flag.AMBIGUOUS)
# The frequencies' relative offsets are measured on at most about this many pixels, evenly spaced: beyond that
# the median's noise is far below the offsets, a few tenths of a millimetre.
OFFSET_SAMPLE_PIXELS = 100_000


def validity_flags(raw: NDArray, options: CorrectionOptions, noise: NoiseModel, confidence: NDArray | None = None,
                   saturation_v2: NDArray | None = None, beyond: BeyondAmbiguity | None = None) -> NDArray[np.uint8]:
    """Flag per pixel of raw rows (n, 2F) [m, V^2]: NOT_NEEDED for valid pixels (the gate decides later), else the
    most basic reason it is invalid.

    Parameters
    ----------
    raw : Raw rows, depths in one range. [m, V^2]
    options : ``min_amplitude_sigmas`` (no return: an amplitude below this many times the no-light noise),
        ``inconsistent_p_value`` (the frequencies disagree beyond chi-square's quantile under ``noise``),
        ``min_unwrap_confidence``, and the deprecated ``max_depth_spread_m`` where given.
    noise : The scan's noise model.
    confidence : The unwrapping's confidence of rows whose depths were unwrapped (:meth:`NoiseModel.unwrap`); rows
        below ``options.min_unwrap_confidence`` are AMBIGUOUS, unless a more basic reason holds.
    saturation_v2 : Each frequency's saturation amplitude (F,) [V^2] (None: ``options.saturation_amplitude_v2``,
        where given, else none).
    beyond : The test for a range past the frequencies' combined ambiguity (None: none).
    """
    f = len(noise.frequencies_hz)
    amplitude = raw[:, f:]
    flags = np.full(raw.shape[0], Flag.NOT_NEEDED, dtype=np.uint8)
    ambiguous = np.zeros(raw.shape[0], bool) if confidence is None else ~(confidence >= options.min_unwrap_confidence)
    rules = [
        (Flag.INCONSISTENT, _inconsistent(raw, options, noise) | _below_zero(raw, noise)),
        (Flag.BEYOND_AMBIGUITY, np.zeros(raw.shape[0], bool) if beyond is None else beyond.flags(raw, noise)),
        (Flag.AMBIGUOUS, ambiguous),
        (Flag.SATURATED, (amplitude >= _saturation_levels(saturation_v2, options, f)[None, :]).any(axis=1)),
        (Flag.NO_RETURN, _no_return(amplitude, options, noise)),
        (Flag.NOT_FINITE, ~np.isfinite(raw).all(axis=1)),
    ]
    for flag, where in rules:  # later rules win: the most basic reason is reported
        flags[where] = flag
    return flags


def _saturation_levels(saturation_v2: NDArray | None, options: CorrectionOptions, f: int) -> NDArray[np.float64]:
    """Each frequency's saturation amplitude (F,) [V^2]: those given, else the options' threshold, else none."""
    if saturation_v2 is not None:
        return np.asarray(saturation_v2, dtype=np.float64)
    return np.full(f, np.inf if options.saturation_amplitude_v2 is None else options.saturation_amplitude_v2)


def _no_return(amplitude: NDArray, options: CorrectionOptions, noise: NoiseModel) -> NDArray[np.bool_]:
    """Rows (n,) whose amplitude at some frequency lies below ``options.min_amplitude_sigmas`` times the noise
    model's no-light noise (its read term: the scan's own where it measured one), or is zero or less."""
    if options.min_amplitude_sigmas == 0:
        return np.zeros(amplitude.shape[0], bool)
    floor = options.min_amplitude_sigmas * noise.floor_v2
    with np.errstate(invalid="ignore"):
        return np.asarray(((amplitude < floor[None, :]) | ~(amplitude > 0)).any(axis=1))


def _inconsistent(raw: NDArray, options: CorrectionOptions, noise: NoiseModel) -> NDArray[np.bool_]:
    """Rows (n,) whose frequencies' depths disagree beyond chi-square's ``1 - options.inconsistent_p_value``
    quantile under the noise model, or spread over more than the deprecated ``max_depth_spread_m`` where given."""
    from scipy.special import chdtri  # the quantile without scipy.stats's imports

    f = len(noise.frequencies_hz)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        inconsistent = noise.chi2(raw) > chdtri(f - 1, options.inconsistent_p_value)
        if options.max_depth_spread_m is not None:
            depth = raw[:, :f]
            high = low = depth[:, 0]
            for column in range(1, f):  # column by column: a row reduction over F values is several times slower
                high, low = np.maximum(high, depth[:, column]), np.minimum(low, depth[:, column])
            inconsistent |= high - low > options.max_depth_spread_m
    return np.asarray(inconsistent)


def _below_zero(raw: NDArray, noise: NoiseModel) -> NDArray[np.bool_]:
    """Rows (n,) whose depth at some frequency lies more than :data:`~mpi_lidar.scans.scan.NOISE_DEVIATIONS` of its
    own noise (the noise law at its amplitude) below zero: no range a surface can have fits them (a near surface
    passes zero by its noise, no more)."""
    f = len(noise.frequencies_hz)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        sigma = noise.depth_sigma_m(raw[:, f:].astype(np.float64))
        return np.asarray((raw[:, :f] < -NOISE_DEVIATIONS * sigma).any(axis=1))


@dataclass(frozen=True)
class BeyondAmbiguity:
    """A range past the frequencies' combined ambiguity L looks by phase like one L nearer; only its amplitude,
    far too weak for the near range, tells it. A pixel is flagged where its amplitude times its range squared over
    Gamma_R (its albedo times the cosine of incidence, were it that near) reads below ``near_albedo`` and would read
    as a plausible surface (at most ``far_albedo``) one ambiguity farther. A dark surface near by reads its own
    albedo, a few per cent at least.

    ambiguity_m : The frequencies' combined ambiguity. [m]
    gamma_r_v2 : The sensor's amplitude of a white surface at 1 m. [V^2 m^2]
    """

    ambiguity_m: float
    gamma_r_v2: float
    near_albedo: float = 0.01
    far_albedo: float = 2.0

    def flags(self, raw: NDArray, noise: NoiseModel) -> NDArray[np.bool_]:
        f = len(noise.frequencies_hz)
        top = int(np.argmax(noise.frequencies_hz))
        with np.errstate(invalid="ignore", over="ignore"):
            range_m = raw[:, top].astype(np.float64)
            amplitude = raw[:, f + top].astype(np.float64)
            near = amplitude * range_m**2 / self.gamma_r_v2
            far = amplitude * (range_m + self.ambiguity_m) ** 2 / self.gamma_r_v2
            return (range_m > 0) & (near < self.near_albedo) & (far <= self.far_albedo) & (amplitude > 0)


def usable_depth_of(raw: NDArray, flags: NDArray) -> NDArray:
    """The highest-frequency depth (n,) [m] of raw rows (n, 2F) whose ``flags`` (n,) are not invalid
    (:data:`INVALID_FLAGS`) or ambiguous, NaN elsewhere: what the scene geometry is worked out from."""
    f = raw.shape[1] // 2
    return np.where(~np.isin(flags, [int(flag) for flag in UNUSABLE_FLAGS]), raw[:, f - 1], np.nan)


def depth_rules_only(options: CorrectionOptions) -> CorrectionOptions:
    """``options`` without amplitude thresholds (no-return floor 0, no saturation threshold): validity from the
    depths alone."""
    return options.model_copy(update={"min_amplitude_sigmas": 0.0, "saturation_amplitude_v2": None})


@dataclass(frozen=True)
class OffsetSample:
    """Every ``stride``-th pixel's depth at each frequency less the highest frequency's (K, F) [m] (NaN where
    invalid), as measured and with the integration window's leakage removed from each
    (:func:`window_corrections_m`): what the frequencies' relative offsets are measured from, once the scene says
    which pixels are free of multipath (:func:`mpi_lidar.correction.baseline.frequency_offsets`)."""

    stride: int
    differences: NDArray[np.float32]
    window_differences: NDArray[np.float32]

    @classmethod
    def empty(cls, pixels: int, frequencies: int) -> OffsetSample:
        stride = max(1, -(-pixels // OFFSET_SAMPLE_PIXELS))
        shape = (-(-pixels // stride), frequencies)
        return cls(stride, np.full(shape, np.nan, dtype=np.float32), np.full(shape, np.nan, dtype=np.float32))

    def fill(self, start: int, rows: NDArray, usable: NDArray, noise: NoiseModel) -> None:
        """The sampled pixels among the rows (n, 2F) of unwrapped raw measurements that start at pixel ``start``
        (``usable`` (n,): valid, of a known range); called only while the validity pass builds the sample."""
        first = -(-start // self.stride) * self.stride - start  # the first sampled pixel in these rows
        picked = np.arange(first, rows.shape[0], self.stride)
        f = self.differences.shape[1]
        depth = rows[picked, :f]
        windowed = depth + window_corrections_m(depth, rows[picked, f:], noise.frequencies_hz, noise.sensor)
        at = (start + picked) // self.stride
        for differences, depths in ((self.differences, depth), (self.window_differences, windowed)):
            differences[at] = np.where(usable[picked, None], depths - depths[:, f - 1:f], np.nan)


@dataclass(frozen=True)
class Validity:
    """The validity stage's result (:func:`check_validity`); flat maps are (H*W,).

    flags : NOT_NEEDED where valid, else why not (:class:`Flag`).
    usable_depth : The highest frequency's depth of the usable pixels (valid, of a known range), NaN elsewhere. [m]
    measured_depth : The highest frequency's depth as measured, unwrapped where the scan's depths were wrapped and
        the unwrapping is certain (as measured where the range is ambiguous). [m]
    confidence : The unwrapping's confidence (None for a scan whose depths came unwrapped). [1]
    offsets : The sample the frequencies' offsets are measured from.
    needs_correction : The pixel-wise gate's decision for every pixel (None: the gate lets every pixel through).
    scan : The scan with its depths in one range: what every later stage reads.
    """

    flags: NDArray[np.uint8]
    usable_depth: NDArray[np.float32]
    measured_depth: NDArray[np.float32]
    confidence: NDArray[np.float32] | None
    offsets: OffsetSample
    needs_correction: NDArray[np.bool_] | None
    scan: Scan


def check_validity(scan: Scan, noise: NoiseModel, options: CorrectionOptions, tiles: list[slice],
                   gate: Gate | None = None, saturation_v2: NDArray | None = None,
                   beyond: BeyondAmbiguity | None = None) -> Validity:
    """Unwrapping and validity of every pixel of ``scan`` (amplitudes in V^2), tile by tile, in one pass
    (:func:`validity_flags`, with ``saturation_v2`` and ``beyond``); with a pixel-wise ``gate``
    (:attr:`Gate.pixel_wise`), its decision for every pixel too."""
    f = len(scan.frequencies_hz)
    size = scan.shape[0] * scan.shape[1]
    flags = np.empty(size, dtype=np.uint8)
    usable_depth = np.empty(size, dtype=np.float32)
    measured = np.empty(size, dtype=np.float32)
    confidence = np.empty(size, dtype=np.float32) if scan.depth_wrapped else None
    needs = np.zeros(size, dtype=bool) if gate is not None and gate.pixel_wise else None
    sample = OffsetSample.empty(size, f)
    moved_parts: list[tuple[NDArray[np.intp], NDArray[np.float32]]] = []
    for pixels, raw in raw_tiles(scan, tiles):
        def check(rows: slice, start: int = pixels.start, raw: NDArray = raw) -> None:
            part, part_confidence = noise.unwrap(raw[rows]) if scan.depth_wrapped else (raw[rows], None)
            part_flags = validity_flags(part, options, noise, part_confidence, saturation_v2, beyond)
            where = slice(start + rows.start, start + rows.stop)
            flags[where] = part_flags
            usable = ~np.isin(part_flags, [int(flag) for flag in UNUSABLE_FLAGS])
            sample.fill(where.start, part, usable, noise)
            usable_depth[where] = usable_depth_of(part, part_flags)
            measured[where] = np.where(part_flags == Flag.AMBIGUOUS, raw[rows, f - 1], part[:, f - 1])
            if needs is not None and gate is not None:
                valid = np.flatnonzero(part_flags == Flag.NOT_NEEDED)
                needs[where.start + valid] = gate.needs_correction(part[valid], noise)
            if confidence is not None and part_confidence is not None:
                confidence[where] = part_confidence
                # Bit by bit: a row that took no wrap count keeps its bytes (NaN included).
                moved = np.flatnonzero((part[:, :f].view(np.uint32) != raw[rows, :f].view(np.uint32)).any(1))
                if moved.size:  # list.append is atomic: the threads' parts need no lock
                    moved_parts.append((where.start + moved, part[moved, :f].copy()))

        on_cores_by_rows(check, raw.shape[0], PARALLEL_MIN_ROWS)
    if moved_parts:  # some depths wrapped: every later stage reads them unwrapped
        moved_parts.sort(key=lambda part: int(part[0][0]))  # each part ascending, disjoint
        scan = unwrapped_scan(scan, np.concatenate([p for p, _ in moved_parts]),
                              np.concatenate([d for _, d in moved_parts]))
    return Validity(flags, usable_depth, measured, confidence, sample, needs, scan)
