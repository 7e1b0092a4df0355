"""The fit's rows and algebra: the two-path model's bias and gain at a footprint A (F6), the surfaces' planes
fitted to their anchors (F7) and the variance those planes add to A (F12).

Rows are (pixel, frequency); docs/explanation/footprint.md carries the equations. The Gauss-Newton fit of A on
this algebra is :class:`mpi_lidar.correction.footprint._fit.FootprintFit`.
"""

from __future__ import annotations

import functools
from typing import Self

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.footprint._surfaces import ANCHOR_SHARE

# A surface with fewer anchors than this has no plane to measure against.
MIN_ANCHOR_PIXELS = 50
# A surface whose anchors lie along a line leaves its plane free to turn about it: the condition number of
# the plane's normal matrix shows it (a few 10^3 on the boards of the benchmarks, above 10^17 on a line).
MAX_PLANE_CONDITION = 1e8
# Rows whose predicted multipath ratio A K exceeds this are left out (there the cap at kappa = 1 leaves the
# depth nothing to say about A).
MAX_FIT_COUPLING = 2.0


class FootprintProblem:
    """The rows of a footprint fit: measured depth and amplitude against the two-path model (F6) and the
    surfaces' planes (F7).

    Parameters
    ----------
    depth, sigma : NDArray
        Measured depth and its noise per row (n, F). [m]
    phasor : NDArray
        The unit-footprint multipath phasor S_f (n, F) (F5). [1]
    coupling : NDArray
        The white coupling K at unit footprint (n,) (F5). [1]
    metres_per_rad : NDArray
        c / 4 pi f per frequency (F,). [m/rad]
    relative_amplitude : NDArray
        Amplitude over Gamma_R (n, F). [1/m^2]
    rays : NDArray
        Unit rays (n, 3).
    surface : NDArray
        Flat-surface label per row (n,).
    reference : NDArray | None
        Reference depth (n,) [m] in place of planes, where given.
    """

    def __init__(self, depth: NDArray, sigma: NDArray, phasor: NDArray, coupling: NDArray, metres_per_rad: NDArray,
                 relative_amplitude: NDArray, rays: NDArray, surface: NDArray, reference: NDArray | None):
        self.depth, self.sigma, self.phasor, self.coupling = depth, sigma, phasor, coupling
        # The bias model in real arithmetic (complex NumPy is several times slower): the phasor's parts.
        self.phasor_re, self.phasor_im = np.ascontiguousarray(phasor.real), np.ascontiguousarray(phasor.imag)
        self.inverse_variance = sigma**-2.0
        self.log_amplitude = np.log(np.maximum(relative_amplitude, 1e-12))
        self.sigma_log = sigma / metres_per_rad
        self.metres_per_rad, self.rays, self.reference = metres_per_rad, rays, reference
        self.labels, self.surface = np.unique(surface, return_inverse=True)
        self.surfaces = int(self.surface.max()) + 1 if surface.size else 0
        # Sums per surface as one matrix product: (surfaces, n) one-hot rows.
        self.members = (self.surface[None, :] == np.arange(self.surfaces)[:, None]).astype(np.float64)
        self.anchor = self._anchor_rows()
        self.ray_outer = np.einsum("ni,nj->nij", rays, rays).reshape(-1, 9)  # the planes' normal equations

    def bias(self, area: float, amplitude: bool = True) -> tuple[NDArray, NDArray, NDArray | None, NDArray | None]:
        """Predicted depth bias (n, F) [m] (F6) at footprint ``area`` [m^2], its derivative in the footprint
        [m/m^2], the amplitude gain |1 + ratio| (n, F) and the derivative of its logarithm [1/m^2] (those two only
        with ``amplitude``, else None)."""
        # ratio = area S / max(area K, 1); with 1 + ratio = x + j y, the derivative of the phase in the
        # footprint is Im(S' / (1 + ratio)) and that of log|1 + ratio| its real part (S' = S / max(area K, 1)).
        coupling = abs(area) * self.coupling
        scale = (1.0 / np.maximum(coupling, 1.0))[:, None]
        s_re, s_im = self.phasor_re * scale, self.phasor_im * scale
        x, y = 1.0 + area * s_re, area * s_im
        bias = np.arctan2(y, x) * self.metres_per_rad
        norm2 = x * x + y * y
        capped = (coupling > 1.0)[:, None] | (norm2 < 1e-18)
        inverse = np.where(capped, 0.0, 1.0 / np.where(capped, 1.0, norm2)) if capped.any() else 1.0 / norm2
        slope = (s_im * x - s_re * y) * inverse * self.metres_per_rad
        if not amplitude:
            return bias, slope, None, None
        gain = np.where(capped, 1.0, np.sqrt(norm2))
        return bias, slope, gain, (s_re * x + s_im * y) * inverse

    def _anchor_and_fit_rows(self) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        """The rows that fix the planes (none against a reference) and the rows A is fitted to."""
        anchor = self.anchor if self.reference is None else np.zeros(self.depth.shape[0], dtype=bool)
        return anchor, (self.coupling > 0) & ~anchor

    def _surface_range(self, bias: NDArray, anchor: NDArray) -> tuple[NDArray, NDArray | None]:
        """The range (n,) each row's depth is measured against, and the planes (None against a reference)."""
        if self.reference is not None:
            return self.reference, None
        return self._plane_range(bias, anchor)

    def _trusted(self, area: float, surface_range: NDArray) -> NDArray[np.bool_]:
        """Rows (n,) the fit at footprint ``area`` uses: coupling within the model's reach, and a surface
        whose plane could be fitted (a surface with too few anchors has no range)."""
        return (abs(area) * self.coupling <= MAX_FIT_COUPLING) & np.isfinite(surface_range)

    def _less_surface_mean(self, values: NDArray, weight: NDArray) -> NDArray:
        """``values`` (n, F) less their ``weight``-ed mean over each surface's rows (its albedo eliminated)."""
        total = np.maximum(np.bincount(self.surface, weight.sum(1), minlength=self.surfaces), 1e-300)
        mean = np.bincount(self.surface, (weight * values).sum(1), minlength=self.surfaces) / total
        return values - mean[self.surface][:, None]

    def _informative(self) -> int:
        """Rows with a facing partner (K > 0)."""
        return int((self.coupling > 0).sum())

    def _plane_noise(self, weighted_slope: NDArray, surface_range: NDArray, bias: NDArray, anchor: NDArray) -> float:
        """The variance the anchors' noise adds to the fit's numerator through the planes, in units of the
        residuals' variance: sum over surfaces of h_s' M_s^-1 h_s (F12).

        A plane u (u . ray = 1 / range) fitted to the anchors with their inverse variances has covariance
        M_s^-1, its normal matrix; a fit row's range then moves by -range^2 ray . du, and the numerator
        sum w g r by h_s . du with h_s the sum over the surface's fit rows of w g range^2 ray. On a narrow
        surface, whose plane rests on a strip of anchors, this term outweighs the fit rows' own noise.
        """
        pull = np.nan_to_num(weighted_slope.sum(1) * surface_range**2)[:, None] * self.rays
        pulls = self.members @ pull
        matrices = self._plane_system(bias, anchor)[0]
        return float(np.einsum("si,si->", pulls, np.linalg.solve(matrices, pulls[..., None])[..., 0]))

    @functools.cached_property
    def with_fixed_planes(self) -> Self:
        """This problem without the surfaces whose anchors cannot fix a plane: too few, or along a line (built
        once: the fit and the second round's partner planes both rest on it).

        A strip along an edge that the multipath bent away from its surface has pixels close to their
        partners only: it has no plane to measure the bias against. A plane its anchors leave free to turn
        could put any bias on its other pixels.
        """
        anchor = self._anchor_rows()
        anchors = np.bincount(self.surface, anchor, minlength=self.surfaces)
        fixed = np.linalg.cond(self._plane_system(np.zeros_like(self.depth), anchor)[0]) < MAX_PLANE_CONDITION
        keep = ((anchors >= MIN_ANCHOR_PIXELS) & fixed)[self.surface]
        kept = type(self)(self.depth[keep], self.sigma[keep], self.phasor[keep], self.coupling[keep],
                          self.metres_per_rad, np.exp(self.log_amplitude[keep]), self.rays[keep], self.surface[keep],
                          None)
        kept.anchor = anchor[keep]
        kept.labels = self.labels[np.unique(self.surface[keep])]
        return kept

    def fixed_planes(self, area: float) -> dict[int, NDArray]:
        """The planes u . x = 1 (u [1/m]) of the surfaces whose anchors fix one (:attr:`with_fixed_planes`),
        fitted to the anchors less the bias predicted at footprint ``area`` [m^2] (F7), by surface label."""
        kept = self.with_fixed_planes
        planes = kept._plane_range(kept.bias(area, amplitude=False)[0], kept.anchor)[1]
        return {int(label): planes[k] for k, label in enumerate(kept.labels)}

    def unbent_planes(self, area: float, through_blocks: dict[int, NDArray]) -> dict[int, NDArray]:
        """The planes of :meth:`fixed_planes` at footprint ``area`` [m^2], by surface label, that explain their
        surface's depths less the bias predicted there better than its plane through the block centres
        (``through_blocks``, u [1/m] by label): a smaller median of the standardized residuals over the surface's
        rows within the model's reach. A plane fitted to anchors that the model's bias does not describe (a small
        surface lit by light it leaves out) misses the rest of its surface and is not taken."""
        kept = self.with_fixed_planes
        bias = kept.bias(area, amplitude=False)[0]
        labels = kept.labels[kept.surface]
        reach = abs(area) * kept.coupling <= MAX_FIT_COUPLING

        def spread(plane: NDArray, rows: NDArray) -> float:
            surface_range = 1.0 / (kept.rays[rows] @ plane)
            z = (kept.depth[rows] - surface_range[:, None] - bias[rows]) / kept.sigma[rows]
            return float(np.median(np.abs(z)))

        better = {}
        for label, plane in self.fixed_planes(area).items():
            rows = (labels == label) & reach
            if label in through_blocks and rows.any() and spread(plane, rows) < spread(through_blocks[label], rows):
                better[label] = plane
        return better

    def _anchor_rows(self) -> NDArray[np.bool_]:
        """Pixels that fix the surfaces' planes: the share ``ANCHOR_SHARE`` of all with the least coupling, and of
        a surface that share leaves under ``MIN_ANCHOR_PIXELS``, its own share with the least coupling.

        A small surface next to a strongly lit one (a room's side wall beside the floor) lies near its partners
        throughout: the global share would leave it no plane, though its own least-coupled pixels fix one.
        """
        if self.coupling.size == 0:
            return np.zeros(0, dtype=bool)
        anchor = self.coupling <= np.quantile(self.coupling, ANCHOR_SHARE)
        short = np.flatnonzero(np.bincount(self.surface, anchor, minlength=self.surfaces) < MIN_ANCHOR_PIXELS)
        for surface in short:
            members = self.surface == surface
            if members.any():
                anchor |= members & (self.coupling <= np.quantile(self.coupling[members], ANCHOR_SHARE))
        return anchor

    def _plane_range(self, bias: NDArray, anchor: NDArray) -> tuple[NDArray, NDArray]:
        """Range (n,) [m] of each pixel's surface plane, fitted to the anchors' depth less the predicted bias (F7).

        The plane u . ray = 1 / range is a weighted least-squares fit per surface of the inverse-variance
        mean depth over the frequencies, each anchor weighted by its range noise (d(1/r) = dr / r^2).
        """
        matrices, vectors = self._plane_system(bias, anchor)
        planes = np.linalg.solve(matrices, vectors[..., None])[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse_range = np.einsum("ni,ni->n", self.rays, planes[self.surface])
            return np.where(inverse_range > 0, 1.0 / inverse_range, np.nan), planes

    def _plane_system(self, bias: NDArray, anchor: NDArray) -> tuple[NDArray, NDArray]:
        """Normal equations (matrices (S, 3, 3), vectors (S, 3)) of the surfaces' planes u . ray = 1 / range (F7),
        fitted to the anchors' inverse-variance mean depth over the frequencies less the predicted bias, each
        anchor weighted by the inverse variance of 1 / range (d(1/r) = dr / r^2)."""
        total = self.inverse_variance.sum(1)
        depth = ((self.depth - bias) * self.inverse_variance).sum(1) / total
        weighted_members = self.members * np.where(anchor, depth**4 * total, 0.0)
        matrices = (weighted_members @ self.ray_outer).reshape(-1, 3, 3) + 1e-9 * np.eye(3)
        return matrices, (weighted_members / depth) @ self.rays
