"""The validity stage: one range from the wrapped depths, and which pixels can be trusted at all (finite, above
the noise floor, unsaturated, frequencies consistent), in one pass over the scan's tiles (:func:`check_validity`).

The same pass keeps what later stages need from the raw measurements, so that they are read only once more after
the scene geometry: a sample of the frequencies' relative depths for their offsets (:class:`OffsetSample`), the
unwrapped depths of the pixels that took a wrap count, and a pixel-wise gate's decision. After the pass, where the
scan holds a pixel past the frequencies' combined ambiguity or a wrap seam, the surfaces joined to them are flagged
too (:func:`~mpi_lidar.correction.beyond_ambiguity.continuity_flags`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.beyond_ambiguity import STEP_SHARE, BeyondAmbiguity, continuity_flags
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
        (Flag.NO_RETURN, _no_return(amplitude, options, noise, _could_be_farther(raw, noise, beyond))),
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


def _no_return(amplitude: NDArray, options: CorrectionOptions, noise: NoiseModel,
               each_frequency: NDArray | None = None) -> NDArray[np.bool_]:
    """Rows (n,) without a return: no light at some frequency (zero or less), or too little at all of them together
    (:func:`unlit`); the rows of ``each_frequency`` (n,) also where some frequency alone lies below
    ``options.min_amplitude_sigmas`` times its no-light noise."""
    if options.min_amplitude_sigmas == 0:
        return np.zeros(amplitude.shape[0], bool)
    weak = unlit(amplitude, options, noise)
    if each_frequency is not None and each_frequency.any():
        rows = np.flatnonzero(each_frequency)
        floor = options.min_amplitude_sigmas * noise.floor_v2
        with np.errstate(invalid="ignore"):
            weak[rows] |= (amplitude[rows] < floor[None, :]).any(axis=1)
    return weak


def unlit(amplitude: NDArray, options: CorrectionOptions, noise: NoiseModel) -> NDArray[np.bool_]:
    """Rows (n,) whose amplitudes (n, F) [V^2] are not all above zero, or whose squared signal-to-noise ratios
    summed over the frequencies (each amplitude over its no-light noise, the noise model's read term) lie below
    chi-square's with 2F degrees of freedom at the false-alarm rate of one frequency at ``options.min_amplitude_sigmas``
    (exp(-k^2 / 2): with no light each amplitude is Rayleigh, its square over the noise chi-square(2)). The
    frequencies' light counts together: four frequencies at 3.2 sds each pass, as one at 5 would alone."""
    from scipy.special import chdtri  # the quantile without scipy.stats's imports

    if options.min_amplitude_sigmas == 0:
        return np.zeros(amplitude.shape[0], bool)
    f = amplitude.shape[1]
    threshold = chdtri(2 * f, np.exp(-options.min_amplitude_sigmas**2 / 2))
    lit = np.ones(amplitude.shape[0], bool)
    snr2 = np.zeros(amplitude.shape[0])
    with np.errstate(invalid="ignore", divide="ignore"):
        for column, floor in enumerate(noise.floor_v2):  # column by column: row reductions are several times slower
            value = amplitude[:, column].astype(np.float64)
            lit &= value > 0
            snr2 += (value / floor) ** 2 if floor > 0 else np.inf
        return np.asarray(~lit | ~(snr2 >= threshold))


def _could_be_farther(raw: NDArray, noise: NoiseModel, beyond: BeyondAmbiguity | None) -> NDArray[np.bool_] | None:
    """Rows (n,) whose amplitude a surface past the ambiguity could give, by its radiometry (None: no unit to
    tell): those keep the no-return floor of each frequency alone, as a lone surface past the ambiguity would
    pass the frequencies' joint floor as a dark near one."""
    if beyond is None or beyond.gamma_r_v2 is None:
        return None
    return beyond.plausible_far(raw, noise)


def _inconsistent(raw: NDArray, options: CorrectionOptions, noise: NoiseModel) -> NDArray[np.bool_]:
    """Rows (n,) whose frequencies' depths disagree beyond chi-square's ``1 - options.inconsistent_p_value``
    quantile under the noise model, or spread over more than the deprecated ``max_depth_spread_m`` where given."""
    f = len(noise.frequencies_hz)
    inconsistent = noise.disagree(raw, options.inconsistent_p_value)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
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
    marks = np.zeros(size, dtype=np.uint8) if beyond is not None else None
    moved_parts: list[tuple[NDArray[np.intp], NDArray[np.float32]]] = []
    for pixels, raw in raw_tiles(scan, tiles):
        def check(rows: slice, start: int = pixels.start, raw: NDArray = raw) -> None:
            part, part_confidence = noise.unwrap(raw[rows]) if scan.depth_wrapped else (raw[rows], None)
            part_flags = validity_flags(part, options, noise, part_confidence, saturation_v2, beyond)
            where = slice(start + rows.start, start + rows.stop)
            flags[where] = part_flags
            if marks is not None and beyond is not None:
                marks[where] = _far_marks(part, part_flags, options, noise, beyond)
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
    if marks is not None and beyond is not None and _may_continue_past(marks):
        marked = {mark: (marks & mark).astype(bool).reshape(scan.shape) for mark in (_LIT, _NODE, _KNOWN, _SEED)}
        far = np.flatnonzero(continuity_flags(scan.depth[f - 1], scan.amplitude[f - 1], marked[_LIT], marked[_NODE],
                                              marked[_KNOWN], marked[_SEED], noise, beyond.ambiguity_m).ravel())
        _flag_beyond(far, flags, usable_depth, sample, needs)
    return Validity(flags, usable_depth, measured, confidence, sample, needs, scan)


# Marks the validity pass keeps of each pixel for the continuity past the ambiguity: a lit pixel (unsaturated), one
# that may lie past it (lit and, where the unit is known, of an amplitude a surface there could give), one of those
# whose range the unwrapping is sure of, one its amplitude surely flags, and one near either end of the ambiguity
# (where a wrap seam may run).
_LIT, _NODE, _KNOWN, _SEED, _NEAR_END, _NEAR_START = 1, 2, 4, 8, 16, 32


def _far_marks(raw: NDArray, flags: NDArray, options: CorrectionOptions, noise: NoiseModel,
               beyond: BeyondAmbiguity) -> NDArray[np.uint8]:
    """The continuity marks (n,) of unwrapped raw rows (n, 2F) [m, V^2] and their flags (n,)."""
    f = len(noise.frequencies_hz)
    lit = (~unlit(raw[:, f:], options, noise) & np.isfinite(raw).all(axis=1)
           & ~np.isin(flags, [int(Flag.SATURATED), int(Flag.NOT_FINITE)]))
    node = lit & beyond.plausible_far(raw, noise)
    known = node & (flags != Flag.AMBIGUOUS)  # a range the unwrapping is sure of
    seed = known & beyond.surely_flags(raw, noise)
    depth = raw[:, f - 1]
    with np.errstate(invalid="ignore"):
        near_end = lit & (depth > (1 - 2 * STEP_SHARE) * beyond.ambiguity_m)
        near_start = known & (depth < 2 * STEP_SHARE * beyond.ambiguity_m)
    marks = (lit * _LIT + node * _NODE + known * _KNOWN + seed * _SEED + near_end * _NEAR_END
             + near_start * _NEAR_START)
    return marks.astype(np.uint8)


def _may_continue_past(marks: NDArray) -> bool:
    """Whether the scan holds a pixel flagged past the ambiguity by its amplitude, or pixels near both of its ends
    (a wrap seam may join them): only then is the continuity worked out."""
    seen = np.bitwise_or.reduce(marks) if marks.size else 0
    return bool(seen & _SEED) or (bool(seen & _NEAR_END) and bool(seen & _NEAR_START))


def _flag_beyond(pixels: NDArray, flags: NDArray, usable_depth: NDArray, sample: OffsetSample,
                 needs: NDArray | None) -> None:
    """The flat ``pixels`` (k,) flagged past the ambiguity by continuity, in the validity pass's maps: their depth
    unusable, out of the offset sample and of the gate's choice."""
    flags[pixels] = Flag.BEYOND_AMBIGUITY
    usable_depth[pixels] = np.nan
    sampled = pixels[pixels % sample.stride == 0] // sample.stride
    sample.differences[sampled] = np.nan
    sample.window_differences[sampled] = np.nan
    if needs is not None:
        needs[pixels] = False
