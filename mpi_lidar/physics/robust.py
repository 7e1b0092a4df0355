"""Robust statistics shared by the geometry, the footprint fit and the sensor calibration."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

# sigma / MAD of a normal distribution, 1 / Phi^-1(3/4): the median absolute deviation times this estimates the
# standard deviation of normal data.
MAD_TO_SIGMA = 1.4826


def robust_sigma(deviations: ArrayLike, axis: int | None = None) -> NDArray[np.float64]:
    """The standard deviation read from deviations about a centre already removed, 1.4826 median|x|.

    Parameters
    ----------
    deviations : Values less their centre (a median, a fitted plane), any unit.
    axis : Axis to reduce over (None: all).

    Returns
    -------
    The robust sigma, in the unit of ``deviations`` (NaN entries are ignored; NaN where none is finite).

    References
    ----------
    .. [1] F. R. Hampel, "The influence curve and its role in robust estimation", JASA 69 (1974) 383-393.
    """
    values = np.abs(np.asarray(deviations, dtype=np.float64))
    with np.errstate(all="ignore"):
        if np.isnan(values).any():
            return MAD_TO_SIGMA * np.asarray(_nanmedian(values, axis))
        return MAD_TO_SIGMA * np.asarray(np.median(values, axis=axis))


def _nanmedian(values: NDArray[np.float64], axis: int | None) -> NDArray[np.float64]:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN slice is NaN, as documented
        return np.asarray(np.nanmedian(values, axis=axis))
