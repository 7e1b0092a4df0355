"""Ranges past the frequencies' combined ambiguity L: a surface there looks by phase like one L nearer.

Two things tell it, each where the other cannot:

- **Its amplitude** (:class:`BeyondAmbiguity`, pixel by pixel, where the amplitudes' unit is known): far too weak
  for a surface at the near range, and plausible for one a whole ambiguity farther.
- **Its continuity** (:func:`continuity_flags`, over the whole scan after the validity pass): a surface that runs
  through L (a floor, a wall seen at a slant) has neighbouring pixels whose depths jump from about L to about 0
  while their amplitudes stay alike: the far side of that wrap seam lies past L, and so does every pixel joined to
  it, or to a pixel the amplitude flags, by a smooth surface (neighbours whose depths and amplitudes differ by no
  more than a surface's do from one pixel to the next).

What neither tells: a lone surface past L, joined to no seam and to no pixel the amplitude flags, whose amplitude
is that of a dark surface at the near range (a white wall at 30 m reads as a 4 % one at 6 m). By phase and
amplitude the two are the same measurement. Such a pixel is kept only where every frequency stands clear of its
no-light noise (:func:`~mpi_lidar.correction.validity.validity_flags`), as for any pixel whose amplitude a surface
past L could give, and is reported at its near range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from mpi_lidar.physics.noise import MIN_AMPLITUDE_V2, NoiseModel
from mpi_lidar.scans.scan import NOISE_DEVIATIONS

# Neighbouring pixels of one smooth surface differ in depth by at most this share of their range (a floor seen from
# 1.5 m at 24 m with 0.2 mrad pixels: 0.3 %; with 5 mrad pixels: 8 %), beyond their noise. Pixels are judged at
# the range they would have past the ambiguity: only the flag past it spreads along these joins.
STEP_SHARE = 0.1
# ... and in amplitude by at most this factor (their ranges' squared ratio, 1.2 at STEP_SHARE, times a change of
# incidence or shade), beyond their noise.
AMPLITUDE_STEP = 2.0
# Joins across scan rows are followed at most this many pixels past the smooth regions' interiors (a surface's
# rim, one or two pixels wide, joins two of them).
MAX_RIM_PIXELS = 64
# The continuity's float maps (depths, amplitudes, their noise and steps) are worked out this many pixels at a time:
# a dozen float32 maps of a whole 4000 x 4000 scan would take most of a GiB.
BAND_PIXELS = 2**20


@dataclass(frozen=True)
class BeyondAmbiguity:
    """A range past the frequencies' combined ambiguity L looks by phase like one L nearer; its amplitude, far too
    weak for the near range, tells it. A pixel is flagged where its amplitude times its range squared over
    Gamma_R (its albedo times the cosine of incidence, were it that near) reads below ``near_albedo`` and would read
    as a plausible surface (at most ``far_albedo``) one ambiguity farther. A dark surface near by reads its own
    albedo, a few per cent at least.

    ambiguity_m : The frequencies' combined ambiguity. [m]
    gamma_r_v2 : The sensor's amplitude of a white surface at 1 m (None: the amplitudes' unit is not known, and
        only continuity tells). [V^2 m^2]
    """

    ambiguity_m: float
    gamma_r_v2: float | None
    near_albedo: float = 0.01
    far_albedo: float = 2.0

    def flags(self, raw: NDArray, noise: NoiseModel) -> NDArray[np.bool_]:
        """Rows (n,) of raw rows (n, 2F) [m, V^2] flagged by their amplitude (none where the unit is not known)."""
        if self.gamma_r_v2 is None:
            return np.zeros(raw.shape[0], bool)
        return self._flagged(*_top_reading(raw, noise), self.gamma_r_v2)

    def surely_flags(self, raw: NDArray, noise: NoiseModel) -> NDArray[np.bool_]:
        """Rows (n,) flagged by their amplitude even ``NOISE_DEVIATIONS`` of its noise higher: those a surface is
        flagged from by continuity (a dark near surface's noisiest pixels are not)."""
        if self.gamma_r_v2 is None:
            return np.zeros(raw.shape[0], bool)
        range_m, amplitude = _top_reading(raw, noise)
        brighter = amplitude + NOISE_DEVIATIONS * _top_quadrature_sd(amplitude, noise)
        return self._flagged(range_m, brighter, self.gamma_r_v2)

    def plausible_far(self, raw: NDArray, noise: NoiseModel) -> NDArray[np.bool_]:
        """Rows (n,) whose amplitude a surface one ambiguity farther could give: it reads at most ``far_albedo``
        there, or the unit is not known to tell."""
        if self.gamma_r_v2 is None:
            return np.ones(raw.shape[0], bool)
        return self._plausible_far(*_top_reading(raw, noise), self.gamma_r_v2)

    def _flagged(self, range_m: NDArray, amplitude: NDArray, gamma_r_v2: float) -> NDArray[np.bool_]:
        """:meth:`flags` of the highest frequency's ranges (n,) [m] and amplitudes (n,) [V^2]."""
        with np.errstate(invalid="ignore"):
            near = _albedo(range_m, amplitude, 0.0, gamma_r_v2) < self.near_albedo
            return near & self._plausible_far(range_m, amplitude, gamma_r_v2)

    def _plausible_far(self, range_m: NDArray, amplitude: NDArray, gamma_r_v2: float) -> NDArray[np.bool_]:
        """:meth:`plausible_far` of the highest frequency's ranges (n,) [m] and amplitudes (n,) [V^2]."""
        with np.errstate(invalid="ignore"):
            return np.asarray(~(_albedo(range_m, amplitude, self.ambiguity_m, gamma_r_v2) > self.far_albedo))


def _top_reading(raw: NDArray, noise: NoiseModel) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The highest frequency's range (n,) [m] and amplitude (n,) [V^2] of raw rows (n, 2F): the only columns the
    test past the ambiguity reads (a float64 copy of two columns, not of the rows)."""
    f = len(noise.frequencies_hz)
    top = int(np.argmax(noise.frequencies_hz))
    return raw[:, top].astype(np.float64), raw[:, f + top].astype(np.float64)


def _top_quadrature_sd(amplitude_v2: NDArray, noise: NoiseModel) -> NDArray[np.float64]:
    """:meth:`NoiseModel.quadrature_sigma_v2` of the highest frequency alone (n,) [V^2] at its amplitudes (n,)
    [V^2]."""
    top = int(np.argmax(noise.frequencies_hz))
    sd = np.sqrt(noise.read_variance_v4[top] + noise.shot_variance_v2[top] * np.maximum(amplitude_v2, 0.0))
    return sd if noise.noise_scale == 1.0 else noise.noise_scale * sd


def _albedo(range_m: NDArray, amplitude: NDArray, farther_m: float, gamma_r_v2: float) -> NDArray[np.float64]:
    """The albedo reading (n,) [1] of ranges (n,) [m] plus ``farther_m`` [m] and amplitudes (n,) [V^2]; NaN where
    the range or the amplitude is not positive."""
    with np.errstate(invalid="ignore", over="ignore"):
        albedo = amplitude * (range_m + farther_m) ** 2 / gamma_r_v2
        return np.where((range_m > 0) & (amplitude > 0), albedo, np.nan)


def continuity_flags(depth_m: NDArray, amplitude_v2: NDArray, lit: NDArray, nodes: NDArray, known: NDArray,
                     seeds: NDArray, noise: NoiseModel, ambiguity_m: float) -> NDArray[np.bool_]:
    """The pixels (H, W) past the ambiguity by continuity: the far sides of wrap seams, the smooth regions most of
    whose pixels ``seeds`` holds, and every pixel of ``nodes`` joined to them by a smooth surface.

    A region is flagged by its amplitude only where most of its pixels are: one pixel's amplitude alone may dip by
    its noise below what any near surface gives, and the surface it belongs to must not follow it.

    Parameters
    ----------
    depth_m : The highest frequency's depth in one range (H, W). [m]
    amplitude_v2 : Its amplitude (H, W). [V^2]
    lit : Pixels with light enough for a range (H, W): a wrap seam's near side may be any of them.
    nodes : Pixels that may lie past the ambiguity (H, W): lit, and (where the unit is known) plausible there.
    known : The nodes whose range the unwrapping is sure of (H, W): only those are a wrap seam's far side (its
        near side, at the range's end, is as often one the unwrapping is unsure of).
    seeds : Pixels flagged past it (H, W) by their amplitude.
    noise : The scan's noise model (the depths' sd at their amplitude).
    ambiguity_m : The frequencies' combined ambiguity L. [m]
    """
    right, down, seam = _joins_and_seams(depth_m, amplitude_v2, lit, nodes, known, noise, ambiguity_m)
    # A seam runs along a surface: its far side continues into more of it (a lone pixel unwrapped by its noise to
    # the far end of the range, beside one at the near end, is no seam).
    seam &= _next_to(nodes, right, down)
    interior, labels, count = _regions(nodes, right, down)
    seeded = np.bincount(labels[seeds & interior], minlength=count + 1) > np.bincount(labels.ravel()) / 2
    seeded[0] = False
    return _joined(seam | seeded[labels], nodes, interior, labels, right, down)


def _joins_and_seams(depth_m: NDArray, amplitude_v2: NDArray, lit: NDArray, nodes: NDArray, known: NDArray,
                     noise: NoiseModel, ambiguity_m: float
                     ) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]]:
    """The smooth joins between neighbouring nodes (right (H, W-1): a pixel and its right neighbour; down
    (H-1, W): a pixel and the one below) and the far sides of wrap seams (H, W) (:func:`continuity_flags`'
    parameters), worked out a band of rows at a time: only the boolean maps are kept whole, the depths' and
    amplitudes' noise and steps (a dozen float maps) only for one band."""
    h, w = nodes.shape
    right = np.zeros((h, max(w - 1, 0)), bool)
    down = np.zeros((max(h - 1, 0), w), bool)
    seam = np.zeros((h, w), bool)
    step = max(1, BAND_PIXELS // max(w, 1))
    for top in range(0, h, step):
        rows = slice(top, min(top + step, h))
        # One row more below: the band's last pixels' joins to the next band's first.
        reach = slice(top, min(top + step + 1, h))
        pixel = (np.asarray(depth_m[reach]), np.asarray(amplitude_v2[reach]),
                 *_top_noise(np.asarray(amplitude_v2[reach]), noise))
        band = {"lit": lit[reach], "nodes": nodes[reach], "known": known[reach]}
        within = rows.stop - top  # the band's own rows among the ``reach`` rows
        right[rows], seam_right = _pair_joins(pixel, band, np.s_[:within, :-1], np.s_[:within, 1:], ambiguity_m)
        down[top:reach.stop - 1], seam_down = _pair_joins(pixel, band, np.s_[:-1, :], np.s_[1:, :], ambiguity_m)
        seam[rows] |= seam_right[:within]
        seam[reach] |= seam_down
    return right, down, seam


def _pair_joins(pixel: tuple[NDArray, ...], band: dict[str, NDArray], first: tuple[slice, ...],
                second: tuple[slice, ...], ambiguity_m: float) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """The smooth joins between the pixels ``first`` and their neighbours ``second`` of one band (depth [m],
    amplitude [V^2], depth sd [m] and amplitude sd [V^2] maps ``pixel``; its ``lit``, ``nodes`` and ``known``
    maps in ``band``), and the band's pixels (its maps' shape) on the far side of a wrap seam between them."""
    a, b = [part[first] for part in pixel], [part[second] for part in pixel]
    lit, nodes, known = band["lit"], band["nodes"], band["known"]
    joins = nodes[first] & nodes[second] & _smooth(a, b, 0.0, ambiguity_m)
    # A wrap seam: the pair's depths jump by about L, and the nearer reading continues the farther one past L.
    seam = np.zeros_like(nodes)
    seam[first] |= known[first] & lit[second] & _smooth(a, b, ambiguity_m, ambiguity_m)
    seam[second] |= known[second] & lit[first] & _smooth(b, a, ambiguity_m, ambiguity_m)
    return joins, seam


def _top_noise(amplitude_v2: NDArray, noise: NoiseModel) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The highest frequency's depth sd [m] and quadrature sd [V^2] (H, W) at its amplitude (H, W) [V^2]."""
    top = int(np.argmax(noise.frequencies_hz))
    amplitude = np.maximum(np.asarray(amplitude_v2, np.float32), np.float32(MIN_AMPLITUDE_V2))
    # Python floats: the maps stay in float32.
    read, shot = float(noise.read_variance_v4[top]), float(noise.shot_variance_v2[top])
    quadrature = (float(noise.noise_scale) * np.sqrt(read + shot * amplitude)).astype(np.float32)
    return (quadrature / amplitude * float(noise.metres_per_radian[top])).astype(np.float32), quadrature


def _smooth(a: list[NDArray], b: list[NDArray], past_m: float, ambiguity_m: float) -> NDArray[np.bool_]:
    """Whether pixel a, its depth read ``past_m`` [m] farther (0 or the ambiguity), and neighbour b would lie on one
    smooth surface past the ambiguity: depths within the noise plus ``STEP_SHARE`` of that range, amplitudes within
    the noise or a factor ``AMPLITUDE_STEP``. ``a`` and ``b``: depth [m], amplitude [V^2], depth sd [m] and
    amplitude sd [V^2] maps of equal shape."""
    (depth_a, amp_a, sigma_a, q_a), (depth_b, amp_b, sigma_b, q_b) = a, b
    with np.errstate(invalid="ignore", divide="ignore"):
        far_a = depth_a + past_m
        range_m = np.maximum(far_a, depth_b) + (ambiguity_m - past_m)
        step = NOISE_DEVIATIONS * np.hypot(sigma_a, sigma_b) + STEP_SHARE * range_m
        alike_depth = np.abs(far_a - depth_b) <= step
        ratio = np.maximum(amp_a, amp_b) / np.minimum(amp_a, amp_b)
        alike_light = (ratio <= AMPLITUDE_STEP) | (np.abs(amp_a - amp_b) <= NOISE_DEVIATIONS * np.hypot(q_a, q_b))
        return np.asarray(alike_depth & alike_light)


def _regions(nodes: NDArray, right: NDArray, down: NDArray) -> tuple[NDArray[np.bool_], NDArray[np.int32], int]:
    """The nodes (H, W) whose every neighbour among the nodes is smooth with them (``right`` (H, W-1): a pixel and
    its right neighbour; ``down`` (H-1, W): a pixel and the one below), their regions' labels (H, W; 0 elsewhere)
    and the number of regions."""
    rough = np.zeros_like(nodes)
    for joins, near, far in ((right, np.s_[:, :-1], np.s_[:, 1:]), (down, np.s_[:-1], np.s_[1:])):
        broken = nodes[near] & nodes[far] & ~joins
        rough[near] |= broken
        rough[far] |= broken
    interior = nodes & ~rough
    labels, count = ndimage.label(interior)
    return interior, labels.astype(np.int32, copy=False), int(count)


def _joined(flagged: NDArray, nodes: NDArray, interior: NDArray, labels: NDArray, right: NDArray,
            down: NDArray) -> NDArray[np.bool_]:
    """``flagged`` (H, W) and every node joined to it through smooth neighbours: the regions of ``labels``
    (:func:`_regions`) whole, and the nodes between them (rims: depth edges, seams) a pixel at a time."""
    reached = flagged.copy()
    for _ in range(MAX_RIM_PIXELS):
        hit = np.zeros(int(labels.max(initial=0)) + 1, bool)
        hit[labels[reached | _next_to(reached, right, down)]] = True
        hit[0] = False
        regions = reached | hit[labels]
        grown = regions | (nodes & ~interior & _next_to(regions, right, down))
        if np.array_equal(grown, reached):
            break
        reached = grown
    return reached


def _next_to(mask: NDArray, right: NDArray, down: NDArray) -> NDArray[np.bool_]:
    """Pixels (H, W) joined to a pixel of ``mask`` (H, W) by a smooth neighbour."""
    near = np.zeros_like(mask)
    near[:, 1:] |= mask[:, :-1] & right
    near[:, :-1] |= mask[:, 1:] & right
    near[1:] |= mask[:-1] & down
    near[:-1] |= mask[1:] & down
    return near
