"""The fit: planes per surface and one footprint A shared by every pixel and frequency.

Rows are (pixel, frequency). Each flat surface s has a plane u_s . x = 1 (u_s [1/m]); a pixel of ray direction t
(unit) lies on it at range 1 / (u_s . t). The plane rests on the surface's anchors, its share ``ANCHOR_SHARE`` of
pixels with the least predicted coupling, less the bias predicted there:

(F7)  minimise over u_s   sum_anchors w (u_s . t - 1 / (d - bias(A)))^2,   w = (d^2 / sigma)^2 summed over f,

d the inverse-variance mean depth over the frequencies. A is fitted to the other pixels' depth d_f against
their plane's range r:

(F8)  d_f = r + bias_f(A) + noise,   noise ~ sigma_f = sigma_q(Gamma_f) / Gamma_f (c / 4 pi f)  [m],

bias_f from (F6), sigma_q the moment model's quadrature noise (:func:`mpi_lidar.correction.validity.depth_noise_m`).
The amplitude gives a second equation per row, one albedo rho_s per surface eliminated:

(F9)  log(Gamma_f / Gamma_R) = log rho_s - log(r^3 |u_s|) + log gain_f(A) + noise,   sigma_log = sigma_f (4 pi f / c),

(F3) with cos_i = 1 / (r |u_s|). Each is a Gauss-Newton fit of the one parameter A,

(F10)  A <- A + sum w g e / sum w g^2,   e the residual, g its derivative in A, w = h / sigma^2,

the derivative g of (F8) including the planes' own motion with A, and h the Huber weights at ``HUBER_K`` robust
spreads s = 1.4826 median|z| of the standardized residuals z (zero beyond six):

(F11)  h = min(1, HUBER_K s / |z|)  for |z| <= 6 s,  else 0.

The statistical variance of A is s^2 / sum w g^2, plus, for the depth, what the anchors' noise adds through the
planes (:meth:`FootprintProblem._plane_noise`):

(F12)  var A = s^2 (1 / I + sum_s h_s' M_s^-1 h_s / I^2),   I = sum w g^2,

M_s the normal matrix of (F7) and h_s the pull of the plane on the numerator. A systematic share of the estimate
(``DEPTH_SYSTEMATIC_SHARE``, ``AMPLITUDE_SYSTEMATIC_SHARE``) is added in quadrature, and the depth's and the
amplitude's estimates are joined in log A:

(F13)  log A = sum_k v_k log A_k / sum_k v_k,   v_k = (A_k / sigma_k)^2,   sigma = A (sum_k v_k)^(-1/2),

where they agree to a factor ``AMPLITUDE_AGREEMENT``; otherwise the scan is not what the model describes and
the estimate is made not significant (sigma >= |A|).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.footprint._problem import FootprintProblem
from mpi_lidar.correction.footprint._result import MIN_INFORMATIVE_PIXELS, EstimateMethod, FootprintEstimate
from mpi_lidar.physics.robust import robust_sigma

# Gauss-Newton: iterations in all, the first of them plain least squares (before A is near, the multipath
# itself looks like an outlier), then Huber weights at this many robust sigmas (nothing beyond six).
MAX_ITERATIONS = 20
PLAIN_ITERATIONS = 4
HUBER_K = 2.0
# The fit stops once a step changes A by less than this share of it: far below the systematic uncertainty.
CONVERGED_STEP = 1e-3
# The amplitude's fit stops at a 1 % step: a tenth of its systematic uncertainty.
AMPLITUDE_STEP = 1e-2
# Relative step of A for the planes' derivative.
PLANE_STEP = 1e-3
# Footprints [m^2] the depth fit may start from: 0 and 1 mm^2 ... 0.5 m^2 in factors of two.
START_GRID_M2 = (0.0, *(1e-3 * 2.0**k for k in range(10)))
# Systematic uncertainty of an estimate, as a share of it: the spread of estimate / truth on rendered corners
# (the depth's 0.19 and the amplitude's 0.08 rms in log where the edge multipath exceeds 2 mm, 0.35 and 0.12
# between 0.5 and 2 mm). The depth's planes take up part of a strong bias (they tilt towards the edge),
# while the amplitude's gain needs no plane of its own beyond each pixel's angle of incidence.
DEPTH_SYSTEMATIC_SHARE = 0.25
AMPLITUDE_SYSTEMATIC_SHARE = 0.1
# ... and, for the amplitude, an error in log amplitude that no footprint explains (the angle of incidence from
# fitted planes, partners beyond the view): 0.7 %, over the fit's leverage d log|1 + ratio| / dA. It is the rms,
# over the main set's corners, of |A_amplitude - A_true| times that leverage; a wide corner's weak coupling
# has little leverage and leaves the estimate to the depth.
AMPLITUDE_SYSTEMATIC_LOG = 7e-3
# The amplitude must tell the same footprint as the depth to this factor.
AMPLITUDE_AGREEMENT = 3.0
# No receiver footprint reaches this [m^2]: a larger estimate is no measurement.
MAX_PLAUSIBLE_M2 = 1.0


@dataclass(frozen=True)
class _Step:
    """One Gauss-Newton step's sums (F10) and the robust spread s of its standardized residuals (F11)."""

    numerator: float
    information: float
    spread: float


@dataclass(frozen=True)
class _AmplitudeStep(_Step):
    """:class:`_Step` of the amplitude rows, with their Huber weights (n, F)."""

    weights: NDArray[np.float64]


@dataclass(frozen=True)
class _DepthStep(_Step):
    """:class:`_Step` of the depth rows, with what the planes' share of the variance (F12) needs: the weights w
    (n, F), derivatives g (n, F), the range measured against (n,) [m], the predicted bias (n, F) [m] and whether
    planes were fitted (not against a reference)."""

    weight: NDArray[np.float64]
    slope: NDArray[np.float64]
    surface_range: NDArray[np.float64]
    bias: NDArray[np.float64]
    on_planes: bool


class FootprintFit(FootprintProblem):
    """Weighted least squares for planes per surface (F7) and one footprint A shared by all pixels and
    frequencies ((F8), (F9)), on the rows and algebra of :class:`FootprintProblem` (its parameters).
    """

    def solve(self, method: EstimateMethod, with_amplitude: bool = True, start_m2: float = 0.0,
              tolerance: float = CONVERGED_STEP) -> FootprintEstimate:
        """The footprint from the depth residuals (over the fitted planes or against the reference depth) and,
        over the planes, from the amplitude.

        Each estimate's statistical uncertainty is combined with a systematic one, a share of the estimate
        (``DEPTH_SYSTEMATIC_SHARE``, ``AMPLITUDE_SYSTEMATIC_SHARE``): their spread over rendered scenes the
        scan's geometry describes only in part (partners beyond the field of view, 3 cm blocks).
        ``with_amplitude``: fit the amplitude too, from the depth's estimate (:meth:`_with_amplitude`).
        ``start_m2``: the footprint the depth fit starts from (an earlier estimate saves iterations; without
        one, the best of a coarse grid, :meth:`_best_start`). ``tolerance``: the relative step of A that ends
        the depth's fit.
        """
        fit = self if self.reference is not None else self.with_fixed_planes
        start_m2 = start_m2 or fit._best_start()
        found = fit._fit_depth(method, start_m2=start_m2, tolerance=tolerance)
        if not np.isfinite(found.area_m2) or abs(found.area_m2) > MAX_PLAUSIBLE_M2:
            # No receiver sees a square metre: such a number comes from a few spurious facing blocks.
            return FootprintEstimate(float("nan"), float("inf"), found.pixels, found.surfaces, (method,))
        depth = replace(found, sigma_m2=float(np.hypot(found.sigma_m2, DEPTH_SYSTEMATIC_SHARE * found.area_m2)))
        if not with_amplitude or self.reference is not None:
            return depth
        return fit._with_amplitude(depth)

    def _best_start(self) -> float:
        """The footprint of :data:`START_GRID_M2` whose depth residuals over the fit rows are smallest (median
        of the standardized residuals, each footprint over the rows it trusts).

        Where the multipath is strong the residuals are not convex in A: the planes, anchored on pixels that
        are themselves biased, take up part of the bias, and a fit started from A = 0 can settle on a second,
        smaller minimum (even a negative footprint) while the true one lies near 0.1 m^2.
        """
        anchor, fit_rows = self._anchor_and_fit_rows()
        best, best_spread = 0.0, np.inf
        for area in START_GRID_M2:
            bias = self.bias(area, amplitude=False)[0]
            surface_range = self._surface_range(bias, anchor)[0]
            rows = fit_rows & self._trusted(area, surface_range)
            if rows.sum() < MIN_INFORMATIVE_PIXELS:
                continue
            z = (self.depth[rows] - surface_range[rows, None] - bias[rows]) / self.sigma[rows]
            spread = float(np.median(np.abs(z)))
            if spread < best_spread:
                best, best_spread = float(area), spread
        return best

    def _with_amplitude(self, depth: FootprintEstimate) -> FootprintEstimate:
        """The depth's estimate joined with the amplitude's (F13): their mean in log A, each weighted by its inverse
        relative variance; not significant where the two differ by more than ``AMPLITUDE_AGREEMENT``.

        Multipath adds light as well as range. A scan whose depth residuals suggest a footprint its
        amplitude does not show (a dark corner, where the predicted bias is tiny and any residual the
        planes leave looks like multipath) is not described by the model. Where they agree, the amplitude
        weighs the more: strong multipath bends each surface near its partners, and the planes the depth is
        measured against take up part of the bias, while the amplitude's gain |1 + ratio| is measured
        against each surface's own albedo (one per surface, eliminated).
        """
        amplitude = self._fit_amplitude(depth.methods[0], start_m2=depth.area_m2, tolerance=AMPLITUDE_STEP)
        depth = replace(depth, depth_m2=depth.area_m2, amplitude_m2=amplitude.area_m2)
        if not (depth.area_m2 > 0 and np.isfinite(amplitude.area_m2) and amplitude.area_m2 > 0
                and 1 / AMPLITUDE_AGREEMENT <= amplitude.area_m2 / depth.area_m2 <= AMPLITUDE_AGREEMENT):
            # The scan is not what the model describes: not significant.
            return replace(depth, sigma_m2=max(depth.sigma_m2, abs(depth.area_m2)))
        systematic = np.hypot(AMPLITUDE_SYSTEMATIC_SHARE * amplitude.area_m2,
                              AMPLITUDE_SYSTEMATIC_LOG / max(self._amplitude_leverage(amplitude.area_m2), 1e-300))
        amplitude = replace(amplitude, sigma_m2=float(np.hypot(amplitude.sigma_m2, systematic)))
        weights = np.array([(e.area_m2 / e.sigma_m2) ** 2 for e in (depth, amplitude)])
        log_area = np.log([depth.area_m2, amplitude.area_m2]) @ weights / weights.sum()
        area = float(np.exp(log_area))
        return replace(depth, area_m2=area, sigma_m2=float(area * weights.sum() ** -0.5))

    def _amplitude_leverage(self, area: float) -> float:
        """Inverse-variance weighted rms of d log|1 + ratio| / dA [1 / m^2] over the rows the amplitude fit
        uses, less its mean per surface (each surface's albedo is eliminated)."""
        bias, _, _, gain_slope = self.bias(area)
        assert gain_slope is not None
        trusted = self._trusted(area, self._plane_range(bias, self.anchor)[0])[:, None]
        weight = np.where(trusted, 1.0 / self.sigma_log**2, 0.0)
        centred = self._less_surface_mean(gain_slope, weight)
        return float(np.sqrt((weight * centred**2).sum() / max(weight.sum(), 1e-300)))

    def _fit_depth(self, method: EstimateMethod, start_m2: float = 0.0, tolerance: float = CONVERGED_STEP
                   ) -> FootprintEstimate:
        """A from the depth rows (F8), over the fitted planes or against the reference depth: the Gauss-Newton fit
        (F10) with the planes' motion in its derivative, its statistical uncertainty (F12)."""
        anchor, fit_rows = self._anchor_and_fit_rows()
        huber = np.ones_like(self.depth)

        def step(area: float, robust: bool) -> _DepthStep:
            nonlocal huber
            bias, slope = self.bias(area, amplitude=False)[:2]
            surface_range, planes = self._surface_range(bias, anchor)
            if planes is not None:
                # The planes move with A (their anchors' predicted bias is taken off): the residual's
                # derivative holds that motion too, or the fit settles where the residuals are not least.
                step_m2 = PLANE_STEP * max(abs(area), 1e-3)
                moved = self._plane_range(bias + step_m2 * slope, anchor)[0]
                slope = slope + ((moved - surface_range) / step_m2)[:, None]
            trusted = self._trusted(area, surface_range)[:, None]
            residual = np.where(trusted, self.depth - np.nan_to_num(surface_range)[:, None] - bias, 0.0)
            z = residual / self.sigma
            spread = float(robust_sigma(z[fit_rows])) or 1.0
            if robust:
                huber = huber_weights(z, spread)
            weight = np.where(trusted & fit_rows[:, None], huber * self.inverse_variance, 0.0)
            return _DepthStep(float((weight * slope * residual).sum()), float((weight * slope**2).sum()), spread,
                              weight, slope, surface_range, bias, planes is not None)

        found = self._gauss_newton(method, start_m2, tolerance, step)
        if isinstance(found, FootprintEstimate):
            return found
        area, last = found
        assert isinstance(last, _DepthStep)
        variance = 1.0 / last.information
        if last.on_planes:
            variance += self._plane_noise(last.weight * last.slope, last.surface_range, last.bias,
                                          anchor) / last.information**2
        return FootprintEstimate(float(area), float(last.spread * np.sqrt(variance)), self._informative(),
                                 self.surfaces, (method,))

    def _fit_amplitude(self, method: EstimateMethod, start_m2: float = 0.0, tolerance: float = CONVERGED_STEP
                       ) -> FootprintEstimate:
        """A from the amplitude rows (F9) over the fitted planes, one albedo per surface eliminated: the
        Gauss-Newton fit (F10) and its statistical uncertainty."""
        anchor = self._anchor_and_fit_rows()[0]
        huber = np.ones_like(self.depth)

        def step(area: float, robust: bool) -> _Step:
            nonlocal huber
            bias, _, gain, gain_slope = self.bias(area)
            surface_range, planes = self._surface_range(bias, anchor)
            if planes is None:  # against a reference there are no planes to give the incidence
                return _Step(0.0, 0.0, 1.0)
            trusted = self._trusted(area, surface_range)[:, None]
            assert gain is not None and gain_slope is not None
            found = self._amplitude_terms(planes, surface_range, gain, gain_slope, trusted, huber, robust)
            huber = found.weights
            return found

        found = self._gauss_newton(method, start_m2, tolerance, step)
        if isinstance(found, FootprintEstimate):
            return found
        area, last = found
        return FootprintEstimate(float(area), float(last.spread * np.sqrt(1.0 / last.information)),
                                 self._informative(), self.surfaces, (method,))

    def _gauss_newton(self, method: EstimateMethod, start_m2: float, tolerance: float,
                      step: Callable[[float, bool], _Step]) -> tuple[float, _Step] | FootprintEstimate:
        """Iterate (F10) from ``start_m2`` [m^2] until a robust step changes A by at most ``tolerance`` of it: A and
        the last step's sums, or an estimate of nothing where there is nothing to measure A on.

        Before A is near, the multipath itself looks like an outlier: ``PLAIN_ITERATIONS`` of plain least squares
        first (``step``'s ``robust`` False), unless the fit starts from an earlier estimate.
        """
        nothing = FootprintEstimate(float("nan"), float("inf"), self._informative(), self.surfaces, (method,))
        if self.depth.shape[0] < 10 or self._informative() == 0:
            return nothing
        area = start_m2
        plain = PLAIN_ITERATIONS if start_m2 == 0 else 0
        for iteration in range(MAX_ITERATIONS):
            robust = iteration >= plain
            last = step(area, robust)
            if last.information <= 0:  # nothing left to measure A on (every row capped or outside the fit)
                return nothing
            change = last.numerator / last.information
            area += change
            if robust and abs(change) <= tolerance * max(abs(area), 1e-4):
                break
        return area, last

    def _amplitude_terms(self, planes: NDArray, surface_range: NDArray, gain: NDArray, gain_slope: NDArray,
                         trusted: NDArray, weights: NDArray, robust: bool) -> _AmplitudeStep:
        """Gauss-Newton sums (F10) of the amplitude rows (F9), their spread and Huber weights (``weights`` as they
        were where not ``robust`` yet)."""
        # Lambertian direct light: amplitude / Gamma_R = rho cos_i / t^2 with cos_i = 1 / (t |u|).
        with np.errstate(divide="ignore", invalid="ignore"):
            log_direct = -np.log(surface_range**3 * np.linalg.norm(planes[self.surface], axis=1))
        residual = np.where(trusted, self.log_amplitude - np.nan_to_num(log_direct)[:, None] - np.log(gain), 0.0)
        weight = np.where(trusted, weights / self.sigma_log**2, 0.0)
        # Eliminate log rho per surface: weighted means.
        residual = self._less_surface_mean(residual, weight)
        slope = self._less_surface_mean(gain_slope, weight)
        z = residual / self.sigma_log
        spread = float(robust_sigma(z)) or 1.0
        if robust:  # the weights of this step's residuals, as the depth's are
            weights = huber_weights(z, spread)
            weight = np.where(trusted, weights / self.sigma_log**2, 0.0)
        return _AmplitudeStep(float((weight * slope * residual).sum()), float((weight * slope**2).sum()), spread,
                              weights)


def huber_weights(z: NDArray, spread: float) -> NDArray:
    """Huber weights (F11) of standardized residuals ``z`` at robust spread ``spread``, zero beyond six spreads."""
    return np.where(np.abs(z) > 6 * spread, 0.0, np.minimum(1.0, HUBER_K * spread / np.maximum(np.abs(z), 1e-12)))
