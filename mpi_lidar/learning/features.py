"""Feature construction and target modes, in one place so training and correction never disagree.

Raw measurements are the per-frequency depths and amplitudes, ordered [depth_f1..depth_fF,
amplitude_f1..amplitude_fF] (the dataset's ``features`` array and a scan's depth/amplitude maps).

Feature sets:
- ``raw``: the paper's 2F inputs as measured.
- ``engineered``: raw, plus what the physics says carries the multipath signature: each depth minus the
  highest-frequency depth, each amplitude over the highest-frequency amplitude, the inverse-variance-weighted
  depth of all frequencies, and the log amplitude of the highest frequency (the signal level, which sets
  the noise).
- ``range_free``: the engineered columns without anything that carries the absolute range: the depth
  differences and amplitude ratios to the highest frequency, the weighted depth minus the highest-frequency
  depth, and the log amplitude of the highest frequency. The multipath bias depends on the A-B distance and
  the reflectances, not on d_AS (the phase offset and the amplitude ratio of the two paths do not involve it);
  range enters only through the amplitude (rho / d^2), which sets the noise. A model on these inputs therefore
  holds at any range whose amplitudes its training rows covered. It needs the residual target. What it gives
  up: the albedo of A, amplitude times squared range, which under the reciprocal prior scales the multipath
  ratio (a rho_ABA); over 0.5-12 m this keeps it 10-30 % above the Bayes limit (docs/results/range-bands.md).

- ``physical`` (the default): the range-free columns plus the log albedo estimate of A, ln(A d^2) of the
  highest frequency [ln(V^2 m^2)] (the albedo times Gamma_R times the incidence cosine): range enters only where
  the physics puts it, the noise (through the amplitude) and the strength of the multipath (the light that
  returns from B is reflected at A again, so the multipath over direct ratio scales with A's albedo).

Depths past the highest frequency's unambiguous range (c / 2f, 4.8 m at 31.25 MHz) are measured wrapped; every
set but ``raw`` takes differences of depths and needs them unwrapped (each frequency's depth within half its
unambiguous range of the others) before :meth:`FeatureSpec.transform`.

Target modes:
- ``absolute``: the true depth d_AS (the paper's target).
- ``residual``: the true depth minus the measured highest-frequency depth; the prediction is a correction.

Geometric inputs (``FeatureSpec.geometric``): two more columns after the feature set's, the rho_ABA and the A-B
distance d_AB that the scan's geometry estimates for the pixel: those of the surface facing the sensor that
would show the pixel's multipath at its amplitude (:meth:`mpi_lidar.scans.geometry.FacingBlocks.equivalent_rho_aba`:
the partners' albedos and the incidence angle are in it). Training rows face the sensor and have no scan, so
:func:`synthetic_geometry` builds the estimate from the row's rho_ABA and d_AB and an estimation error
(docs/results/geometry.md, section 3b).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING, overload

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.feature_choices import (  # light for the command line; the defaults are re-exported
    DEFAULT_FEATURE_SET,  # noqa: F401
    DEFAULT_GEOMETRIC,  # noqa: F401
    DEFAULT_TARGET_MODE,  # noqa: F401
    FEATURE_SETS,
    RELATIVE_FEATURE_SETS,
    TARGET_MODES,
    FeatureSet,
    TargetMode,
)
from mpi_lidar.simulation.dataset import frequency_labels, raw_feature_names

if TYPE_CHECKING:
    import dask.array as da
    from typing_extensions import TypeIs

# Amplitudes below this are treated as no return when forming ratios and logs. [V^2]
AMPLITUDE_FLOOR_V2 = 1e-12
GEOMETRIC_NAMES = ("geometric_rho_aba", "geometric_d_ab_m")
# Error of the geometric estimates the training rows get: the estimated rho_ABA is the true one times a
# log-normal factor of median 1 and log-spread 0.2, the d_AB estimate 0.2 cm long with an sd of 1.1 cm (the
# medians and within-scene spreads over the rendered corners of docs/results/geometry.md, section 1, of the per-pixel
# estimates from the partner planes). Those corners read rho_ABA 1.07-1.22x with the true footprint given and
# a spread of about 0.1 in log within a scene; with the footprint the scan measures (the default) the
# calibration, which rests on the same model, takes that factor up, and its own scatter widens the spread.
GEOMETRY_ERROR_MODEL: dict[str, float] = {
    "coupling_log_median": 0.0, "coupling_log_sd": 0.2,
    "d_ab_offset_m": 0.002, "d_ab_sd_m": 0.011,
}
# Stream of the dataset's seed tree reserved for the synthetic geometry (chunks use (i,), summaries (2**31,)).
GEOMETRY_STREAM = 2**31 + 1


def row_uniforms(seed: int, rows: NDArray) -> NDArray[np.float64]:
    """Four uniforms in (0, 1) per row index (n, 4), a function of (seed, row) only. [1]

    A Philox counter stream keyed by the dataset seed: row r uses the counter r, so any subset or chunking of
    the rows (train on Dask blocks, a tuning subsample, the test split) gets the same values for a row.
    """
    rows = np.asarray(rows, dtype=np.int64).ravel()
    if rows.size == 0:
        return np.zeros((0, 4))
    first, last = int(rows.min()), int(rows.max())
    if first < 0:
        raise MpiLidarError(f"row indices must be >= 0, got {first}")
    key = np.random.SeedSequence(seed, spawn_key=(GEOMETRY_STREAM,)).generate_state(2, np.uint64)
    bit_generator = np.random.Philox(key=key)
    bit_generator.advance(first)
    raw = bit_generator.random_raw(4 * (last - first + 1)).reshape(-1, 4)[rows - first]
    return ((raw >> np.uint64(11)).astype(np.float64) + 0.5) * 2.0**-53


def synthetic_geometry(theta: NDArray, theta_names: tuple[str, ...] | list[str], seed: int, rows: NDArray,
                       error_model: dict[str, float] | None = None) -> NDArray[np.float64]:
    """The geometric estimates (rho_ABA [1], d_AB [m]) a scan would give for training rows (n, 2).

    A training row faces the sensor, so the equivalent rho_ABA the geometry estimates is the row's own. As
    set in :data:`GEOMETRY_ERROR_MODEL`: rho_ABA estimate = rho_ABA exp(mu + s z1), d_AB estimate =
    max(d_AB + offset + sd z2, 0), with z1, z2 standard normal. Rows with rho_ABA = 0 (no partner) get
    (0, 0), as the geometry gives no partner there. Randomness from :func:`row_uniforms` (seed, row).
    """
    model = {**GEOMETRY_ERROR_MODEL, **(error_model or {})}
    theta = np.asarray(theta, dtype=np.float64)
    names = list(theta_names)
    rho, d_ab = theta[:, names.index("rho_aba")], theta[:, names.index("d_ab_m")]
    u = row_uniforms(seed, rows)
    if u.shape[0] != theta.shape[0]:
        raise MpiLidarError(f"{theta.shape[0]} theta rows but {u.shape[0]} row indices")
    radius = np.sqrt(-2.0 * np.log(u[:, 0]))
    z1, z2 = radius * np.cos(2 * np.pi * u[:, 1]), radius * np.sin(2 * np.pi * u[:, 1])
    estimate = rho * np.exp(model["coupling_log_median"] + model["coupling_log_sd"] * z1)
    distance = np.maximum(d_ab + model["d_ab_offset_m"] + model["d_ab_sd_m"] * z2, 0.0)
    partner = rho > 0
    return np.column_stack([np.where(partner, estimate, 0.0), np.where(partner, distance, 0.0)])


def geometry_inputs(rho_aba: NDArray, d_ab_m: NDArray) -> NDArray[np.float64]:
    """Geometric model inputs (n, 2) from a scan's estimates: rho_ABA [1] and d_AB [m], 0 where no partner."""
    rho_aba = np.nan_to_num(np.asarray(rho_aba, dtype=np.float64).ravel(), nan=0.0)
    d_ab = np.nan_to_num(np.asarray(d_ab_m, dtype=np.float64).ravel(), nan=0.0)
    return np.column_stack([rho_aba, np.where(rho_aba > 0, d_ab, 0.0)])


def weighted_depth(raw: NDArray, frequencies_hz: tuple[float, ...]) -> NDArray[np.float64]:
    """Single-path multi-frequency depth: each depth weighted by its inverse noise variance. [m]

    The phase noise of a frequency scales as sigma / Gamma_f and its depth noise as that over f, so the
    weight is (f Gamma_f)^2 (the per-bin noise sigma is common to all frequencies).
    """
    n_freq = len(frequencies_hz)
    depth = np.asarray(raw[:, :n_freq], dtype=np.float64)
    amplitude = np.asarray(raw[:, n_freq:], dtype=np.float64)
    weights = (np.asarray(frequencies_hz)[None, :] * amplitude) ** 2
    total = weights.sum(1)
    safe = np.where(total > 0, total, 1.0)
    return np.where(total > 0, (weights * depth).sum(1) / safe, depth[:, -1])


@dataclass(frozen=True)
class FeatureSpec:
    """How raw measurements become model inputs and how a prediction becomes a depth."""

    frequencies_hz: tuple[float, ...]
    feature_set: FeatureSet = "raw"
    target_mode: TargetMode = "absolute"
    geometric: bool = False

    def __post_init__(self) -> None:
        if self.feature_set not in FEATURE_SETS:
            raise MpiLidarError(f"unknown feature set {self.feature_set!r}; choose one of {', '.join(FEATURE_SETS)}")
        if self.target_mode not in TARGET_MODES:
            raise MpiLidarError(f"unknown target mode {self.target_mode!r}; choose one of {', '.join(TARGET_MODES)}")
        if self.feature_set in RELATIVE_FEATURE_SETS and self.target_mode == "absolute":
            raise MpiLidarError(f"the {self.feature_set} feature set holds no absolute depth, so it cannot predict "
                                "one: use target mode 'residual'")

    @property
    def n_freq(self) -> int:
        return len(self.frequencies_hz)

    @property
    def raw_names(self) -> list[str]:
        return raw_feature_names(self.frequencies_hz)

    @property
    def names(self) -> list[str]:
        names = self.raw_names if self.feature_set in ("raw", "engineered") else []
        if self.feature_set != "raw":
            labels = frequency_labels(self.frequencies_hz)
            top = labels[-1]
            names += [f"depth_{x}_minus_{top}" for x in labels[:-1]]
            names += [f"amplitude_{x}_over_{top}" for x in labels[:-1]]
            names += ["weighted_depth" if self.feature_set == "engineered" else f"weighted_depth_minus_{top}",
                      f"log_amplitude_{top}"]
        if self.feature_set == "physical":
            names.append(f"log_albedo_{top}")
        if self.geometric:
            names += list(GEOMETRIC_NAMES)
        return names

    @property
    def residual_reference(self) -> str | None:
        """The measured depth column the residual target is relative to."""
        return self.raw_names[self.n_freq - 1] if self.target_mode == "residual" else None

    @overload
    def transform(self, raw: NDArray, geometry: NDArray | None = None) -> NDArray[np.float32]: ...

    @overload
    def transform(self, raw: da.Array, geometry: NDArray | da.Array | None = None) -> da.Array: ...

    def transform(self, raw: NDArray | da.Array, geometry: NDArray | da.Array | None = None,
                  ) -> NDArray[np.float32] | da.Array:
        """Model inputs from raw measurements (n, 2F), numpy or dask (block by block).

        ``geometry`` (n, 2): the geometric rho_ABA [1] and d_AB [m] per row; required when ``geometric``,
        ignored otherwise.
        """
        self._require_geometry(geometry)
        if is_dask_array(raw):
            import dask.array as da  # loaded already: raw is a dask array

            lazy = raw.rechunk({1: -1})
            base = len(self.names) - (len(GEOMETRIC_NAMES) if self.geometric else 0)
            features = da.map_blocks(self._transform_block, lazy, dtype=np.float32, chunks=(lazy.chunks[0], (base,)))
            if not self.geometric:
                return features
            extra = da.asarray(geometry).astype(np.float32).rechunk((lazy.chunks[0], -1))
            return da.concatenate([features, extra], axis=1).rechunk({1: -1})
        raw = self._checked(raw)
        return self.transform_into(raw, geometry, np.empty((raw.shape[0], len(self.names)), dtype=np.float32))

    def transform_into(self, raw: NDArray, geometry: NDArray | da.Array | None, out: NDArray[np.float32]
                       ) -> NDArray[np.float32]:
        """:meth:`transform` of numpy rows written into ``out`` (n, len(names)) float32, which is returned.

        Each column is worked out in float64 and rounded once to float32, as a float64 matrix of all the
        features rounded at the end would be, without that matrix: rows can be split among threads, each
        filling its own rows of one array.
        """
        self._require_geometry(geometry)
        base = len(self.names) - (len(GEOMETRIC_NAMES) if self.geometric else 0)
        self._transform_block(raw, out[:, :base])
        if self.geometric:
            geometry = np.asarray(geometry)
            if geometry.shape != (out.shape[0], len(GEOMETRIC_NAMES)):
                raise MpiLidarError(f"expected geometric inputs of shape ({out.shape[0]}, 2), got {geometry.shape}")
            out[:, base:] = geometry
        return out

    def _require_geometry(self, geometry: object) -> None:
        if self.geometric and geometry is None:
            raise MpiLidarError("this model was trained with geometric features (rho_ABA, d_AB) and needs them "
                                "for every pixel: give a scan with geometry (azimuth/elevation or ray directions)")

    def _checked(self, raw: NDArray) -> NDArray:
        raw = np.asarray(raw)
        if raw.ndim != 2 or raw.shape[1] != 2 * self.n_freq:
            raise MpiLidarError(f"expected raw measurements of shape (n, {2 * self.n_freq}), got {raw.shape}")
        return raw

    def _transform_block(self, raw: NDArray, out: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
        raw = self._checked(raw)
        if self.feature_set == "raw":
            if out is None:
                return raw.astype(np.float32, copy=False)
            out[:] = raw
            return out
        f = self.n_freq
        engineered = self.feature_set == "engineered"
        physical = self.feature_set == "physical"
        if out is None:
            out = np.empty((raw.shape[0], 4 * f if engineered else 2 * f + physical), dtype=np.float32)
        if engineered:
            out[:, :2 * f] = raw  # rounded to float32 like every column (exact for float32 measurements)
        _relative_columns(raw, self.frequencies_hz, out[:, 2 * f:] if engineered else out[:, :2 * f],
                          weighted_from_top=not engineered)
        if physical:
            top_amplitude = np.maximum(raw[:, 2 * f - 1].astype(np.float64), AMPLITUDE_FLOOR_V2)
            out[:, 2 * f] = np.log(top_amplitude * np.square(raw[:, f - 1].astype(np.float64)))
        return out

    @overload
    def reference_depth(self, raw: NDArray) -> NDArray: ...

    @overload
    def reference_depth(self, raw: da.Array) -> da.Array: ...

    def reference_depth(self, raw: NDArray | da.Array) -> NDArray | da.Array:
        """The measured depth a residual is relative to (zero for the absolute target). [m]"""
        if self.target_mode == "absolute":
            return raw[:, 0] * 0.0
        return raw[:, self.n_freq - 1].astype(np.float64)

    @overload
    def target(self, raw: NDArray, true_depth: NDArray) -> NDArray: ...

    @overload
    def target(self, raw: da.Array, true_depth: da.Array) -> da.Array: ...

    def target(self, raw: NDArray | da.Array, true_depth: NDArray | da.Array) -> NDArray | da.Array:
        """What the model learns: the true depth, or the true depth minus the reference depth. [m]"""
        return true_depth - self.reference_depth(raw)

    @overload
    def depth(self, raw: NDArray, prediction: NDArray) -> NDArray: ...

    @overload
    def depth(self, raw: da.Array, prediction: da.Array) -> da.Array: ...

    def depth(self, raw: NDArray | da.Array, prediction: NDArray | da.Array) -> NDArray | da.Array:
        """Corrected depth from a prediction. [m]"""
        return self.reference_depth(raw) + prediction



def _relative_columns(raw: NDArray, frequencies_hz: tuple[float, ...], out: NDArray[np.float32],
                      weighted_from_top: bool) -> None:
    """The columns relative to the highest frequency, written into ``out`` (n, 2F) in the order of the names.

    Depth differences [m] and amplitude ratios [1] to the highest frequency, the weighted depth (absolute, or
    minus the highest-frequency depth with ``weighted_from_top``) [m], and the log highest amplitude
    [log V^2]. Each column is worked out in float64 and rounded once into ``out``.
    """
    f = len(frequencies_hz)
    top_depth = raw[:, f - 1].astype(np.float64)
    top_amplitude = np.maximum(raw[:, 2 * f - 1].astype(np.float64), AMPLITUDE_FLOOR_V2)
    for k in range(f - 1):
        out[:, k] = raw[:, k].astype(np.float64) - top_depth
        out[:, f - 1 + k] = np.maximum(raw[:, f + k].astype(np.float64), AMPLITUDE_FLOOR_V2) / top_amplitude
    weighted = weighted_depth(raw, frequencies_hz)
    out[:, 2 * f - 2] = weighted - top_depth if weighted_from_top else weighted
    out[:, 2 * f - 1] = np.log(top_amplitude)


def is_dask_array(values: object) -> TypeIs[da.Array]:
    """Whether ``values`` is a dask array, without importing dask (if it is not loaded, it cannot be one)."""
    module = sys.modules.get("dask.array")
    return module is not None and isinstance(values, module.Array)


def synthetic_geometry_dask(theta: da.Array, theta_names: tuple[str, ...] | list[str], seed: int) -> da.Array:
    """:func:`synthetic_geometry` for all rows of a lazy theta (n, k), block by block, rows numbered from 0."""
    import dask.array as da  # only where a dask array is built: the rest of the module stays light

    theta = theta.rechunk({1: -1})
    rows = da.arange(theta.shape[0], chunks=theta.chunks[0], dtype=np.int64)[:, None]

    def block(t: NDArray, r: NDArray) -> NDArray[np.float64]:
        return synthetic_geometry(t, theta_names, seed, r[:, 0])

    return da.map_blocks(block, theta, rows, dtype=np.float64, chunks=(theta.chunks[0], (len(GEOMETRIC_NAMES),)))
