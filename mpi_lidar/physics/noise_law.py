"""A scan's own noise law, measured from how much its frequencies disagree (:func:`measure_noise_law`).

Each frequency's depth variance follows the sensor's law, sigma_f^2 = c_r R_f / A_f^2 + c_s S_f / A_f: a read term
(thermal and amplifier noise, the same at any light) and a shot term (in proportion to the light), with R_f and
S_f the reference law's coefficients in depth units (:class:`~mpi_lidar.physics.noise.NoiseModel`: its quadrature
variance line times (c / 4 pi f)^2) and c_r, c_s the two constants a scan measures. Two frequencies of one pixel
see the same range, so their difference d_f - d_g (less its median: a fixed offset between them) has variance
sigma_f^2 + sigma_g^2: linear in (c_r, c_s), whatever the amplitudes' unit. The constants are the weighted least
squares of the squared differences of every pair of frequencies of every pixel, each weighted by its predicted
variance (the square of a normal difference has variance 2 E^2), with the pairs beyond chi-square(1)'s 0.999
quantile left out (wrong wrap counts, depth edges, strong multipath) and the mean of what is kept corrected for
that cut.

A unit u of the amplitudes scales c_r by u^2 and c_s by u and nothing else: the law is measured in the scan's own
unit, and fusion, unwrapping and the consistency test need no other. A constant the data cannot tell from zero
(the read term on a scan of bright surfaces alone) is fitted as zero: over the amplitudes the scan holds, the other
term then carries the whole noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.physics.noise import NoiseModel

# Pixels a law is measured from at least, and the most relative sd of the variance it predicts at the median pixel
# for it to be significant.
MIN_LAW_PIXELS = 200
MAX_RELATIVE_SIGMA = 0.1
# Squared differences beyond this many times their predicted variance are left out: chi-square(1)'s 0.999 quantile.
CUT_CHI2 = 10.828
ROUNDS = 6


@dataclass(frozen=True)
class NoiseLaw:
    """A scan's noise law (:func:`measure_noise_law`), relative to a reference law.

    read_scale : c_r, the read term over the reference's, in the squared amplitude unit of the rows. [1]
    shot_scale : c_s, the shot term over the reference's, in the amplitude unit of the rows. [1]
    read_sigma : Standard error of c_r. [1]
    shot_sigma : Standard error of c_s. [1]
    pixels : Pixels measured.
    relative_sigma : Relative standard error of the depth variance the law predicts at the median pixel. [1]
    significant : At least ``MIN_LAW_PIXELS`` pixels and that variance known to ``MAX_RELATIVE_SIGMA``.
    reason : Why not, where it is not significant.
    """

    read_scale: float
    shot_scale: float
    read_sigma: float
    shot_sigma: float
    pixels: int
    relative_sigma: float
    significant: bool
    reason: str = ""

    def model(self, reference: NoiseModel) -> NoiseModel:
        """The reference model with this law's constants (its noise scale 1: the law holds the whole noise)."""
        return NoiseModel(reference.frequencies_hz, reference.speed_of_light_m_per_s,
                          self.read_scale * reference.read_variance_v4, self.shot_scale * reference.shot_variance_v2,
                          1.0, reference.sensor)


def measure_noise_law(rows: NDArray, reference: NoiseModel) -> NoiseLaw:
    """The noise law of raw rows (n, 2F) of depths in one range [m] and amplitudes in any unit, relative to
    ``reference`` (the module's docstring).

    Parameters
    ----------
    rows : Raw rows, depths unwrapped (a wrong wrap count is left out as an outlier). [m, any amplitude unit]
    reference : The law whose coefficients the constants scale (its own noise scale is ignored).

    Returns
    -------
    NoiseLaw
        The constants, their standard errors, and whether they are significant.
    """
    f = len(reference.frequencies_hz)
    rows = np.asarray(rows, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(rows).all(1) & (rows[:, f:] > 0).all(1)
    rows = rows[keep]
    n = rows.shape[0]
    if n < MIN_LAW_PIXELS:
        return NoiseLaw(float("nan"), float("nan"), float("inf"), float("inf"), n, float("inf"), False,
                        f"only {n} pixels with finite depths and amplitudes, at least {MIN_LAW_PIXELS} needed")
    squared, read_x, shot_x = _pair_terms(rows, reference)
    scales, covariance = _fit(squared, read_x, shot_x, f)
    at = np.array([np.median(read_x), np.median(shot_x)])
    predicted = float(at @ scales)
    relative = float(np.sqrt(max(at @ covariance @ at, 0.0))) / predicted if predicted > 0 else float("inf")
    significant = bool(np.isfinite(relative) and relative <= MAX_RELATIVE_SIGMA)
    reason = "" if significant else (f"its depth variance is known only to {relative:.2g} (relative sigma), more "
                                     f"than {MAX_RELATIVE_SIGMA:g}")
    errors = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    return NoiseLaw(float(scales[0]), float(scales[1]), float(errors[0]), float(errors[1]), n, relative, significant,
                    reason)


def _pair_terms(rows: NDArray, reference: NoiseModel) -> tuple[NDArray, NDArray, NDArray]:
    """Each pair of frequencies' squared difference less its median (n * P,), and the read and shot terms it is
    the sum of (n * P,) each, at the reference's constants."""
    f = len(reference.frequencies_hz)
    metres2 = reference.metres_per_radian**2
    read = reference.read_variance_v4 * metres2 / rows[:, f:] ** 2  # (n, F) [m^2] at c_r = 1
    shot = reference.shot_variance_v2 * metres2 / rows[:, f:]  # (n, F) [m^2] at c_s = 1
    squared, read_x, shot_x = [], [], []
    for a, b in combinations(range(f), 2):
        difference = rows[:, a] - rows[:, b]
        squared.append((difference - np.median(difference)) ** 2)
        read_x.append(read[:, a] + read[:, b])
        shot_x.append(shot[:, a] + shot[:, b])
    return np.concatenate(squared), np.concatenate(read_x), np.concatenate(shot_x)


def _fit(squared: NDArray, read_x: NDArray, shot_x: NDArray, frequencies: int) -> tuple[NDArray, NDArray]:
    """(c_r, c_s) and their covariance (2, 2): iteratively reweighted, trimmed least squares, each constant at
    least zero (a term the data cannot tell from zero is fitted as zero)."""
    from scipy.special import chdtr

    # Where to start: one constant for both terms, from the median (chi-square(1)'s median is 0.4549).
    start = float(np.median(squared / (read_x + shot_x))) / 0.4549
    if not np.isfinite(start) or start <= 0:  # the frequencies agree exactly: no scatter to measure a law from
        return np.zeros(2), np.full((2, 2), np.inf)
    predicted = start * (read_x + shot_x)
    scales = np.array([start, start])
    design = np.column_stack([read_x, shot_x])
    for _ in range(ROUNDS):
        kept = squared <= CUT_CHI2 * predicted
        weight = 1.0 / predicted[kept] ** 2
        scales = _nonnegative_wls(design[kept], squared[kept], weight)
        # A law of zero where no pair has scatter left: keep the weights finite.
        predicted = np.maximum(design @ scales, 1e-6 * start * (read_x + shot_x))
    # The mean of chi-square(1) cut at CUT_CHI2 is this share of the whole mean: the kept squares read it low.
    kept_mean = float(chdtr(3, CUT_CHI2) / chdtr(1, CUT_CHI2))
    scales = scales / kept_mean
    kept = squared <= CUT_CHI2 * predicted
    weighted = design[kept] / predicted[kept, None]
    # Var(y) = 2 E^2; the P pairs of a pixel carry only F - 1 independent differences.
    pairs = frequencies * (frequencies - 1) / 2
    try:
        covariance = 2.0 * np.linalg.inv(weighted.T @ weighted) * pairs / (frequencies - 1)
    except np.linalg.LinAlgError:
        covariance = np.full((2, 2), np.inf)
    return scales, covariance / kept_mean**2


def _nonnegative_wls(design: NDArray, target: NDArray, weight: NDArray) -> NDArray[np.float64]:
    """Weighted least squares of ``target`` on the columns of ``design`` (m, 2), each coefficient at least zero."""
    root = np.sqrt(weight)
    # Columns scaled to one norm first: an amplitude unit scales them apart by its square, which the solution must
    # follow exactly.
    norms = np.maximum(np.linalg.norm(design * root[:, None], axis=0), 1e-300)
    both = np.linalg.lstsq(design * root[:, None] / norms, target * root, rcond=None)[0] / norms
    if (both >= 0).all():
        return both
    best = np.zeros(2)
    best_cost = np.inf
    for column in range(2):  # one term alone
        x = design[:, column] * root
        value = max(float(x @ (target * root)) / max(float(x @ x), 1e-300), 0.0)
        cost = float(np.sum((target * root - value * x) ** 2))
        if cost < best_cost:
            best, best_cost = np.eye(2)[column] * value, cost
    return best
