"""Two-path inverse solvers: from depth and amplitude at equally spaced frequencies back to (d_AS, d_AB).

At frequency f_k the measured correlation is the phasor z_k = A_k exp(+i phi_k), with A_k the amplitude
(eq 6) and phi_k = 4 pi f_k d_k / c the phase (eq 5, 7), in the sign convention of
:mod:`mpi_lidar.physics.transport` (:func:`~mpi_lidar.physics.transport.path_phasor`). The two-path model
(eq 11-15) says

    z_k = Gamma_D exp(+i w_k d_AS) + Gamma_M exp(+i w_k (d_AS + d_AB)),    w_k = 4 pi f_k / c,

with Gamma_D, Gamma_M independent of frequency (eq 12-13). When the frequencies are equally spaced,
f_k = f_1 + k * df (12.5, 18.75, 25, 31.25 MHz: df = 6.25 MHz), z_k is a sum of two exponentials in k,
c_D u^k + c_M v^k with poles u = exp(+i 4 pi df d_AS / c) and v = exp(+i 4 pi df (d_AS + d_AB) / c):
Prony's method recovers the poles from a 2-term linear recurrence, then the amplitudes by least squares.

The multipath phase offset w_k d_AB is at most ~0.2 rad here, so the two poles lie within ~0.04 rad of each
other and the fit is badly conditioned: with Table I noise it is usually worse than the raw depth. The
solvers report a per-row status and fall back to the single-path weighted depth where the fit degenerates:

- ``FIT_OK`` (0): a two-path fit within the constraints.
- ``SINGLE_PATH`` (1): one path explains the data (Gamma_M -> 0, or d_AB -> 0 where the poles merge);
  the direct depth is the single-path depth.
- ``OUT_OF_BOUNDS`` (2): the fit violated a constraint (d_AB outside [0, max_offset_m], Gamma_M > max_ratio
  * Gamma_D, non-physical amplitudes) or did not converge; the direct depth is the fallback.
- ``NOT_FINITE`` (3): the input row has a non-finite or non-positive value; every output is 0.

Constraints: d_AB >= 0 (the multipath travels further); 0 <= Gamma_M <= max_ratio * Gamma_D with
max_ratio = 1 by default, because Gamma_M / Gamma_D = rho_SAB rho_ABA rho_BAS / rho_SAS (eq 12-13), which
is a * (kappa b) <= 1 under the reciprocal prior (rho_SAS = rho_SAB = rho_BAS = a); d_AB <= max_offset_m
(default 0.15 m, the prior's upper bound), below the 24 m the base step can tell apart.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mpi_lidar.constants import TABLE_SPEED_OF_LIGHT_M_PER_S
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.physics.transport import path_phasor, phasor

DEFAULT_MAX_OFFSET_M = 0.15
DEFAULT_MAX_RATIO = 1.0

FIT_OK = np.uint8(0)
SINGLE_PATH = np.uint8(1)
OUT_OF_BOUNDS = np.uint8(2)
NOT_FINITE = np.uint8(3)
STATUS_NAMES = {0: "fit_ok", 1: "single_path", 2: "out_of_bounds", 3: "not_finite"}

# Relative size below which a Hankel determinant, a pole separation or an amplitude ratio counts as zero.
DEGENERATE_TOL = 1e-9
# sigma_min / sigma_max of the linear-prediction matrix below which it counts as rank one (one path).
RANK_TOL = 1e-7


@dataclass(frozen=True)
class TwoPathFit:
    """Per-row result of a two-path solver, all arrays of shape (n,).

    direct_depth_m : estimate of d_AS, finite everywhere (the fallback where the fit degenerates). [m]
    path_offset_m : estimate of d_AB (0 where no second path was fitted). [m]
    direct_amplitude : Gamma_D. [V^2]
    multipath_amplitude : Gamma_M (0 where no second path was fitted). [V^2]
    status : uint8 code, see the module docstring.
    cost : sum of squared phasor residuals over the squared mean amplitude. [1]
    """

    direct_depth_m: NDArray[np.float64]
    path_offset_m: NDArray[np.float64]
    direct_amplitude: NDArray[np.float64]
    multipath_amplitude: NDArray[np.float64]
    status: NDArray[np.uint8]
    cost: NDArray[np.float64]


def frequency_step(frequencies_hz: ArrayLike, rtol: float = 1e-9) -> float:
    """The common step df of equally spaced frequencies (at least 4 of them, increasing). [Hz]"""
    freqs = np.asarray(frequencies_hz, dtype=np.float64)
    if freqs.ndim != 1 or freqs.size < 4:
        raise MpiLidarError(f"a two-path fit needs at least 4 frequencies, got {freqs.size}")
    steps = np.diff(freqs)
    if steps[0] <= 0 or not np.allclose(steps, steps[0], rtol=rtol, atol=0):
        raise MpiLidarError(
            f"the two-path solvers need equally spaced increasing frequencies, got {list(freqs / 1e6)} MHz"
        )
    return float(steps[0])


def measured_phasors(raw: ArrayLike, frequencies_hz: ArrayLike, c: float = TABLE_SPEED_OF_LIGHT_M_PER_S):
    """z_k = A_k exp(+i 4 pi f_k d_k / c) from raw rows (n, 2F) [m, V^2], eq 5-7 inverted. [V^2]"""
    raw = np.asarray(raw, dtype=np.float64)
    freqs = np.asarray(frequencies_hz, dtype=np.float64)
    f = freqs.size
    if raw.ndim != 2 or raw.shape[1] != 2 * f:
        raise MpiLidarError(f"expected raw measurements of shape (n, {2 * f}), got {raw.shape}")
    depth, amplitude = raw[:, :f], raw[:, f:]
    return path_phasor(amplitude, depth, freqs[None, :], c)


def model_phasors(direct_depth_m: ArrayLike, path_offset_m: ArrayLike, direct_amplitude: ArrayLike,
                  multipath_amplitude: ArrayLike, frequencies_hz: ArrayLike,
                  c: float = TABLE_SPEED_OF_LIGHT_M_PER_S) -> NDArray[np.complex128]:
    """Two-path phasors Gamma_D e^{+i w d_AS} + Gamma_M e^{+i w (d_AS + d_AB)}, shape (n, F), eq 11-15. [V^2]"""
    w = 4 * np.pi * np.asarray(frequencies_hz, dtype=np.float64)[None, :] / c
    d = np.asarray(direct_depth_m, dtype=np.float64)[:, None]
    e = np.asarray(path_offset_m, dtype=np.float64)[:, None]
    gd = np.asarray(direct_amplitude, dtype=np.float64)[:, None]
    gm = np.asarray(multipath_amplitude, dtype=np.float64)[:, None]
    return phasor(1.0, w * d) * (gd + phasor(gm, w * e))


def _valid_rows(raw: NDArray[np.float64], f: int) -> NDArray[np.bool_]:
    return np.all(np.isfinite(raw), axis=1) & np.all(raw[:, f:] > 0, axis=1)


def unwrapped_weighted_depth(raw: ArrayLike, frequencies_hz: ArrayLike,
                             c: float = TABLE_SPEED_OF_LIGHT_M_PER_S) -> NDArray[np.float64]:
    """Single-path depth of equally spaced frequencies, unambiguous to c / (2 df) (24 m here). [m]

    The phase step between neighbouring frequencies, arg sum_k z_{k+1} conj(z_k), gives a coarse depth
    that no single frequency's wrap affects; each frequency's depth is unwrapped next to it (d_k + n_k c / 2 f_k)
    and the unwrapped depths are averaged with inverse-variance weights (f_k A_k)^2, as the weighted depth of
    :func:`mpi_lidar.learning.features.weighted_depth` does (which, without unwrapping, is wrong once d_AS passes the
    highest frequency's range, 4.8 m).

    Parameters
    ----------
    raw : Measurements (n, 2F). [m, V^2]
    frequencies_hz : Equally spaced modulation frequencies (F,). [Hz]
    c : Speed of light. [m/s]
    """
    freqs = np.asarray(frequencies_hz, dtype=np.float64)
    step = frequency_step(freqs)
    raw = np.asarray(raw, dtype=np.float64)
    z = measured_phasors(raw, freqs, c)
    f = freqs.size
    coarse = _path_from_pole((z[:, 1:] * z[:, :-1].conj()).sum(axis=1), step, c)
    ranges = c / (2 * freqs)
    depth = _unwrap_near(raw[:, :f], ranges[None, :], coarse[:, None])
    weights = (freqs[None, :] * raw[:, f:]) ** 2
    total = weights.sum(axis=1)
    return np.where(total > 0, (weights * depth).sum(axis=1) / np.where(total > 0, total, 1.0), coarse)


def _fallback(raw: NDArray[np.float64], freqs: NDArray[np.float64], valid: NDArray[np.bool_], c: float):
    """Single-path estimate: unwrapped inverse-variance weighted depth and mean amplitude (0 on invalid rows)."""
    f = freqs.size
    safe = np.where(valid[:, None], raw, 1.0)
    depth = np.where(valid, unwrapped_weighted_depth(safe, freqs, c), 0.0)
    amplitude = np.where(valid, safe[:, f:].mean(axis=1), 0.0)
    return depth, amplitude


def _cost(z: NDArray[np.complex128], model: NDArray[np.complex128]) -> NDArray[np.float64]:
    scale = np.maximum(np.abs(z).mean(axis=1), 1e-300) ** 2
    return (np.abs(model - z) ** 2).sum(axis=1) / scale


def _path_from_pole(pole: NDArray[np.complex128], step_hz: float, c: float) -> NDArray[np.float64]:
    """Path length from a pole u = exp(+i 4 pi df d / c), in [0, c / 2 df). [m]"""
    return np.mod(np.angle(pole), 2 * np.pi) * c / (4 * np.pi * step_hz)


def _unwrap_near(phase_path_m: NDArray[np.float64], period_m: float | NDArray[np.float64], near_m: NDArray[np.float64]):
    """The path congruent to ``phase_path_m`` modulo ``period_m`` that is closest to ``near_m``. [m]"""
    return phase_path_m + np.round((near_m - phase_path_m) / period_m) * period_m


def _svd_lstsq(a: NDArray[np.complex128], b: NDArray[np.complex128]):
    """Least-squares solutions of a stack of small systems a x = b, (n, m, k) and (n, m), and a's singular values.

    Normal equations would square the condition number, which is ~1e5 here (poles 0.04 rad apart).
    """
    u, sv, vh = np.linalg.svd(a, full_matrices=False)
    inv = np.divide(1.0, sv, out=np.zeros_like(sv), where=sv > RANK_TOL * sv[:, :1])
    y = inv * np.einsum("nmj,nm->nj", u.conj(), b)
    x = np.einsum("nji,nj->ni", vh.conj(), y)
    return x, sv


def _rows(raw: ArrayLike, frequencies_hz: ArrayLike, c: float) -> tuple[NDArray, ...]:
    """Float64 rows, their phasors, validity and single-path fallback (depth, amplitude): both solvers start here."""
    freqs = np.asarray(frequencies_hz, dtype=np.float64)
    raw = np.asarray(raw, dtype=np.float64)
    valid = _valid_rows(raw, freqs.size)
    return freqs, raw, measured_phasors(raw, freqs, c), valid, *_fallback(raw, freqs, valid, c)


def prony_two_path(raw: ArrayLike, frequencies_hz: ArrayLike, *, max_offset_m: float = DEFAULT_MAX_OFFSET_M,
                   max_ratio: float = DEFAULT_MAX_RATIO, c: float = TABLE_SPEED_OF_LIGHT_M_PER_S) -> TwoPathFit:
    """Closed-form two-path fit (Prony / matrix pencil with two poles), vectorised over rows.

    The phasors z_0..z_{F-1} of equally spaced frequencies obey z_{k+2} + a1 z_{k+1} + a0 z_k = 0 for two
    exponentials; (a1, a0) follow by least squares (exactly for F = 4), the poles are the roots of
    x^2 + a1 x + a0, and (c_D, c_M) solve the Vandermonde system. The shorter path is the direct one. Each
    path length comes from its pole (unambiguous to c / 2 df = 24 m) and is refined by the phase of its
    amplitude at the lowest frequency, unwrapped next to it. A rank-1 Hankel matrix or merged poles give
    ``SINGLE_PATH``; constraint violations give ``OUT_OF_BOUNDS``; both fall back to the weighted depth.

    Parameters
    ----------
    raw : Measurements (n, 2F), [depth_1..depth_F, amplitude_1..amplitude_F]. [m, V^2]
    frequencies_hz : Equally spaced modulation frequencies (F,), F >= 4. [Hz]
    max_offset_m : Largest accepted d_AB. [m]
    max_ratio : Largest accepted Gamma_M / Gamma_D. [1]
    c : Speed of light. [m/s]
    """
    freqs, raw, z, valid, fallback_depth, fallback_amplitude = _rows(raw, frequencies_hz, c)
    step = frequency_step(freqs)
    f, n = freqs.size, raw.shape[0]
    z = np.where(valid[:, None], z, 1.0)

    # Linear prediction: [z_{k+1}, z_k] @ (a1, a0) = -z_{k+2}, k = 0..F-3, by SVD least squares.
    a = np.stack([z[:, 1:-1], z[:, :-2]], axis=-1)  # (n, F-2, 2)
    sol, sv = _svd_lstsq(a, -z[:, 2:])
    rank_one = sv[:, -1] <= RANK_TOL * sv[:, 0]
    a1, a0 = np.where(rank_one, 0.0, sol[:, 0]), np.where(rank_one, 0.0, sol[:, 1])
    root = np.sqrt(a1 * a1 - 4 * a0)
    poles = np.stack([(-a1 + root) / 2, (-a1 - root) / 2], axis=1)  # (n, 2)
    paths = _path_from_pole(poles, step, c)
    order = np.argsort(paths, axis=1)
    poles = np.take_along_axis(poles, order, axis=1)
    u, v = poles[:, 0], poles[:, 1]
    merged = rank_one | (np.abs(u - v) <= DEGENERATE_TOL * np.maximum(np.abs(u) + np.abs(v), 1e-300))

    # Amplitudes: least squares on the Vandermonde system z_k = c_D u^k + c_M v^k.
    k = np.arange(f)
    u_safe: NDArray[np.complex128] = np.where(merged, 1.0, u)
    v_safe: NDArray[np.complex128] = np.where(merged, 0.5, v)
    vander = np.stack([u_safe[:, None] ** k, v_safe[:, None] ** k], axis=-1)  # (n, F, 2)
    amps, _ = _svd_lstsq(vander, z)
    c_d, c_m = amps[:, 0], amps[:, 1]
    gamma_d, gamma_m = np.abs(c_d), np.abs(c_m)

    # Path lengths: coarse from the poles, fine from the amplitudes' phases at the lowest frequency.
    coarse_d = _path_from_pole(u_safe, step, c)
    coarse_m = _path_from_pole(v_safe, step, c)
    period = c / (2 * freqs[0])
    fine_d = _unwrap_near(_path_from_pole(c_d, freqs[0], c), period, coarse_d)
    fine_m = _unwrap_near(_path_from_pole(c_m, freqs[0], c), period, coarse_m)
    offset = fine_m - fine_d

    finite = np.isfinite(fine_d) & np.isfinite(offset) & np.isfinite(gamma_d) & np.isfinite(gamma_m)
    single = merged | (gamma_m <= DEGENERATE_TOL * gamma_d)
    inside = (offset >= 0) & (offset <= max_offset_m) & (gamma_m <= max_ratio * gamma_d) & (gamma_d > 0)
    status = np.full(n, OUT_OF_BOUNDS, dtype=np.uint8)
    status[finite & inside & ~single] = FIT_OK
    status[single] = SINGLE_PATH
    status[~valid] = NOT_FINITE
    ok = status == FIT_OK
    direct = np.where(ok, fine_d, fallback_depth)
    offset = np.where(ok, offset, 0.0)
    gamma_d = np.where(ok, gamma_d, fallback_amplitude)
    gamma_m = np.where(ok, gamma_m, 0.0)
    cost = np.where(valid, _cost(z, model_phasors(direct, offset, gamma_d, gamma_m, freqs, c)), 0.0)
    return TwoPathFit(direct, offset, gamma_d, gamma_m, status, cost)


def _lm_solve(z: NDArray[np.complex128], w: NDArray[np.float64], start: NDArray[np.float64],
              lower: NDArray[np.float64], upper: NDArray[np.float64], iterations: int):
    """Batched projected Levenberg-Marquardt on p = (d_AS, d_AB, Gamma_D, r = Gamma_M / Gamma_D).

    Residuals: real and imaginary parts of (model - z) / mean |z|, eq 11-15. Returns (p, cost, converged).
    """
    n = z.shape[0]
    scale = np.maximum(np.abs(z).mean(axis=1), 1e-300)[:, None]
    zs = z / scale

    def residual_and_jacobian(p: NDArray[np.float64], rows: NDArray[np.intp]):
        d, e, g, r = (p[:, i : i + 1] for i in range(4))
        ed = phasor(1.0, w * d) / scale[rows]
        ee = phasor(1.0, w * e)
        model = ed * (g + g * r * ee)
        res = model - zs[rows]
        rr = np.concatenate([res.real, res.imag], axis=1)
        cols = [1j * w * model, 1j * w * ed * g * r * ee, ed * (1 + r * ee), ed * g * ee]
        jac = np.stack([np.concatenate([col.real, col.imag], axis=1) for col in cols], axis=-1)
        return rr, jac

    p = np.clip(start, lower, upper)
    rr, jac = residual_and_jacobian(p, np.arange(n))
    cost = (rr**2).sum(axis=1)
    lam = np.full(n, 1e-3)
    converged = np.zeros(n, dtype=bool)
    eye = np.eye(4)
    for _ in range(iterations):
        active = ~converged
        if not active.any():
            break
        ja, ra = jac[active], rr[active]
        diag = (ja**2).sum(axis=1)
        damping = lam[active, None] * (diag + 1e-12 * diag.max(axis=1, keepdims=True) + 1e-300)
        # Step from the augmented system [J; sqrt(damping)] step = [-r; 0] by QR: the normal equations
        # would square J's condition number (~1e6 where the poles nearly merge).
        aug = np.concatenate([ja, np.sqrt(damping)[:, :, None] * eye], axis=1)
        rhs = np.concatenate([-ra, np.zeros((ra.shape[0], 4))], axis=1)
        q_mat, r_mat = np.linalg.qr(aug)
        step = np.linalg.solve(r_mat, np.einsum("nki,nk->ni", q_mat, rhs)[..., None])[..., 0]
        trial = np.clip(p[active] + step, lower, upper)
        idx = np.flatnonzero(active)
        rr_t, jac_t = residual_and_jacobian(trial, idx)
        cost_t = (rr_t**2).sum(axis=1)
        better = cost_t < cost[active]
        gain = cost[active] - cost_t
        # Converged: a negligible decrease, or no step that decreases the cost even at huge damping.
        done = (better & (gain <= 1e-7 * cost[active])) | (~better & (lam[active] > 1e10))
        done |= cost_t < 1e-26
        upd = idx[better]
        p[upd], rr[upd], jac[upd], cost[upd] = trial[better], rr_t[better], jac_t[better], cost_t[better]
        lam[upd] = np.maximum(lam[upd] / 3, 1e-12)
        lam[idx[~better]] *= 4
        converged[idx[done]] = True
    return p, cost, converged


def least_squares_two_path(raw: ArrayLike, frequencies_hz: ArrayLike, start: TwoPathFit | None = None, *,
                           max_offset_m: float = DEFAULT_MAX_OFFSET_M, max_ratio: float = DEFAULT_MAX_RATIO,
                           iterations: int = 200, c: float = TABLE_SPEED_OF_LIGHT_M_PER_S) -> TwoPathFit:
    """Bounded nonlinear least-squares two-path fit of the phasors, vectorised over rows.

    Minimises sum_k |Gamma_D e^{+i w_k d_AS} (1 + r e^{+i w_k d_AB}) - z_k|^2 (eq 11-15; the phasor noise
    has about the same variance at every frequency) over d_AS, 0 <= d_AB <= max_offset_m, Gamma_D >= 0 and
    0 <= r = Gamma_M / Gamma_D <= max_ratio, by a batched projected Levenberg-Marquardt iteration from several
    starts (``start``, by default the Prony fit where it succeeded, and a small grid of (d_AB, r) around the
    single-path depth); the lowest cost wins. The fit is defined even where one path explains the data:
    r -> 0 or d_AB -> 0 gives ``SINGLE_PATH`` with the fitted (single-path) depth; a fit that did not
    converge gives ``OUT_OF_BOUNDS`` with the weighted-depth fallback.

    Parameters
    ----------
    raw : Measurements (n, 2F), [depth_1..depth_F, amplitude_1..amplitude_F]. [m, V^2]
    frequencies_hz : Modulation frequencies (F,). [Hz]
    start : Starting point; rows whose status is not FIT_OK are ignored. Default: :func:`prony_two_path`.
    max_offset_m : Upper bound of d_AB. [m]
    max_ratio : Upper bound of Gamma_M / Gamma_D. [1]
    iterations : Iteration limit per start.
    c : Speed of light. [m/s]
    """
    freqs, raw, z, valid, fallback_depth, fallback_amplitude = _rows(raw, frequencies_hz, c)
    n = raw.shape[0]
    if start is None:
        start = prony_two_path(raw, freqs, max_offset_m=max_offset_m, max_ratio=max_ratio, c=c)
    w = 4 * np.pi * freqs[None, :] / c
    lower = np.array([-np.inf, 0.0, 0.0, 0.0])
    upper = np.array([np.inf, max_offset_m, np.inf, max_ratio])
    zv = z[valid]
    best_p = np.zeros((zv.shape[0], 4))
    best_cost = np.full(zv.shape[0], np.inf)
    best_conv = np.zeros(zv.shape[0], dtype=bool)
    starts = []
    ok = (start.status == FIT_OK)[valid]
    sp = np.column_stack([start.direct_depth_m, start.path_offset_m, start.direct_amplitude,
                          start.multipath_amplitude / np.maximum(start.direct_amplitude, 1e-300)])[valid]
    single = np.column_stack([fallback_depth, np.zeros(n), fallback_amplitude, np.zeros(n)])[valid]
    starts.append(np.where(ok[:, None], sp, single))
    for e_frac in (0.25, 0.75):
        for r in (0.2, 0.6):
            r = min(r, max_ratio)
            grid = single.copy()
            grid[:, 1] = e_frac * max_offset_m
            grid[:, 3] = r
            # Move d_AS back by the phase bias this path adds at the highest frequency (eq 11).
            wt = w[0, -1]
            bias = np.arctan2(r * np.sin(wt * grid[:, 1]), 1 + r * np.cos(wt * grid[:, 1])) / wt
            grid[:, 0] = single[:, 0] - bias
            grid[:, 2] = single[:, 2] / np.abs(1 + phasor(r, wt * grid[:, 1]))
            starts.append(grid)
    for p0 in starts:
        p, cost, conv = _lm_solve(zv, w, p0.copy(), lower, upper, iterations)
        better = cost < best_cost
        best_p[better], best_cost[better], best_conv[better] = p[better], cost[better], conv[better]

    direct = fallback_depth.copy()
    offset = np.zeros(n)
    gamma_d = fallback_amplitude.copy()
    gamma_m = np.zeros(n)
    cost = np.zeros(n)
    status = np.full(n, NOT_FINITE, dtype=np.uint8)
    finite = np.isfinite(best_p).all(axis=1) & np.isfinite(best_cost)
    good = best_conv & finite
    tol = 1e-6
    single_path = (best_p[:, 3] <= tol * max(max_ratio, 1e-300)) | (best_p[:, 1] <= tol * max_offset_m)
    st = np.where(good, np.where(single_path, SINGLE_PATH, FIT_OK), OUT_OF_BOUNDS).astype(np.uint8)
    # A single-path fit has no second path: its offset and multipath amplitude are 0 by convention.
    keep = st != OUT_OF_BOUNDS
    vi = np.flatnonzero(valid)
    direct[vi[keep]] = best_p[keep, 0]
    offset[vi[keep]] = np.where(st[keep] == FIT_OK, best_p[keep, 1], 0.0)
    gamma_d[vi[keep]] = best_p[keep, 2] * np.where(st[keep] == FIT_OK, 1.0, 1.0 + best_p[keep, 3])
    gamma_m[vi[keep]] = np.where(st[keep] == FIT_OK, best_p[keep, 2] * best_p[keep, 3], 0.0)
    cost[vi] = np.where(finite, best_cost, 0.0)
    status[vi] = st
    return TwoPathFit(direct, offset, gamma_d, gamma_m, status, cost)
