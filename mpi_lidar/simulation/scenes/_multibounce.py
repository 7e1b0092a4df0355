"""Multi-bounce light transport with occlusion: light that returns to a scan direction's point A after one or
more bounces among the scene's surfaces, over patches (a radiosity of the room lit by the beam's spot).

The beam deposits unit power at A (albedo a, incidence cos_i). Patches j (centre, normal, area dA_j, albedo
b_j) exchange it; a patch is seen from a point, or from another patch, only where both face each other and no
planar surface of the scene crosses the segment between them (:class:`Occluders`). Three operators carry it:

    out_Aj = a cos_A cos_j dA_j / (pi r^2)              power reaching patch j from A,
    T_jk   = b_j cos_j cos_k dA_k / (pi r^2)            power reaching patch k per unit reaching patch j,
    back_jA = b_j cos_j cos_A A_fp / (pi r^2)           power reaching A's footprint A_fp per unit reaching j,

each with the phase e^{j 2 pi f s / c} of its segment's length s. Light that reaches the footprint with power
P returns P / cos_i of the direct path's light (the scene renderer's convention, :mod:`mpi_lidar.physics.coupling`),
so the multipath ratio Gamma_M / Gamma_D of paths through n patches is

    ratio_n = out T^(n-1) back / cos_i,

at n = 1 the two-path kernel a b (cos_A cos_B)^2 dA_B A_fp / (pi^2 r^4 cos_i) with the phase of d_AS + r of
today's single-bounce transport (A -> B -> A), at n = 2 the paths A -> B -> C -> A, and so on up to ``bounces``.
The n = 1 term sums over fine patches (the scene's patch spacing), the higher ones over coarser patches, both
graded: a patch next to another surface is the finest, and grows with its distance from every other surface,
where the kernel changes slowly. Every r is clamped below by the patch's side (the single-bounce term's by the
patch spacing, as the single-bounce transport), a point's or a patch's total outgoing share (sum out / a, sum
T_jk / b_j) is held at most 1, and the white single-bounce coupling caps the sum at kappa = 1 as there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config
from mpi_lidar.physics.coupling import footprint_area, pair_geometry
from mpi_lidar.physics.transport import harmonic_multiples, path_phasor
from mpi_lidar.scans.scan import grid_rays
from mpi_lidar.simulation.scenes._geometry import Rectangle, Scene, first_hits, surface_hits

DEFAULT_BOUNCES = 3
# Every single-bounce patch grows by its finest side (the patch spacing) for every GRADING_M [m] it lies from
# every other surface ...
GRADING_M = 0.06
# ... and the higher bounces' patches, COARSE_FACTOR times as wide next to another surface, every COARSE_GRADING_M.
COARSE_FACTOR = 5.0
COARSE_GRADING_M = 0.15
# Pixels worked on at once: their (pixels, patches, frequencies) arrays stay near 100 MB.
PIXEL_BLOCK = 256
# A point this close to a plane [m] lies on it (the end of a segment never crosses its own surface).
ON_PLANE_M = 1e-7
# A wavenumber [rad/m] small enough that Im(sum w e^{j k s}) / k is the weighted path length sum w s.
PROBE_WAVENUMBER = 1e-3


@dataclass(frozen=True)
class Patches:
    """Patches of all surfaces: centres (M, 3) [m], unit normals (M, 3), areas (M,) [m^2], albedos (M,), the index
    of their surface (M,), whether light leaves both their sides (M,) and the distance their r is clamped at (M,)
    [m]."""

    centres: NDArray[np.float64]
    normals: NDArray[np.float64]
    areas: NDArray[np.float64]
    albedo: NDArray[np.float64]
    surface: NDArray[np.intp]
    two_sided: NDArray[np.bool_]
    clamp_m: NDArray[np.float64]

    @property
    def size(self) -> int:
        return int(self.areas.size)


def scene_patches(scene: Scene, spacing_m: float, grading_m: float | None = GRADING_M) -> Patches:
    """Every surface's patches: ``spacing_m`` [m] wide, next to another surface where graded, growing by
    ``spacing_m`` every ``grading_m`` [m] further from all the others (None: uniform, each surface's own
    :meth:`~Surface.patches`, r clamped at ``spacing_m`` as the single-bounce transport does)."""
    parts = []
    samples = [s.patches(spacing_m)[0] for s in scene.surfaces]
    for index, surface in enumerate(scene.surfaces):
        if grading_m is None or not isinstance(surface, Rectangle):
            centres, normals, areas = surface.patches(spacing_m)
        else:
            others = [samples[k] for k in range(len(samples)) if k != index]
            centres, normals, areas = graded_rectangle(surface, spacing_m, grading_m,
                                                       np.concatenate(others) if others else np.zeros((0, 3)))
        clamp = np.full(areas.size, spacing_m) if grading_m is None else np.maximum(np.sqrt(areas), spacing_m)
        parts.append((centres, normals, areas, np.full(areas.size, surface.albedo), np.full(areas.size, index),
                      np.full(areas.size, surface.two_sided), clamp))
    centres, normals, areas, albedo, which, two_sided, clamp = (np.concatenate(p) for p in zip(*parts, strict=True))
    return Patches(centres, normals, areas, albedo, which.astype(np.intp), two_sided.astype(bool), clamp)


def graded_rectangle(rectangle: Rectangle, finest_m: float, grading_m: float, others: NDArray
                     ) -> tuple[NDArray, NDArray, NDArray]:
    """A rectangle's patches (centres (m, 3) [m], normals (m, 3), areas (m,) [m^2]), halved until each is at most
    ``finest_m`` (1 + d / ``grading_m``) wide, d [m] its clearance from the points ``others`` (k, 3) of the other
    surfaces."""
    from scipy.spatial import cKDTree  # imported where used: the start-up does not pay for it

    c, u, v = (np.asarray(x, dtype=np.float64) for x in (rectangle.centre, rectangle.half_u, rectangle.half_v))
    normal = np.cross(u, v) / np.linalg.norm(np.cross(u, v))
    length_u, length_v = 2 * np.linalg.norm(u), 2 * np.linalg.norm(v)
    top = 16 * finest_m
    nu, nv = max(1, round(length_u / top)), max(1, round(length_v / top))
    grid_s, grid_t = np.meshgrid((np.arange(nu) + 0.5) / nu * 2 - 1, (np.arange(nv) + 0.5) / nv * 2 - 1,
                                 indexing="ij")
    s, t = grid_s.ravel(), grid_t.ravel()
    ds, dt = np.full(s.size, 2.0 / nu), np.full(s.size, 2.0 / nv)  # cell sides in the [-1, 1] parameters
    tree = cKDTree(others) if others.shape[0] else None
    done = []
    while s.size:
        points = c + s[:, None] * u + t[:, None] * v
        side_u, side_v = ds * length_u / 2, dt * length_v / 2
        distance = tree.query(points)[0] if tree is not None else np.full(s.size, np.inf)
        clearance = np.maximum(distance - 0.5 * np.hypot(side_u, side_v), 0.0)
        split = np.maximum(side_u, side_v) > finest_m * (1 + clearance / grading_m)
        done.append((points[~split], side_u[~split] * side_v[~split]))
        quarter_s, quarter_t = ds[split] / 4, dt[split] / 4
        s = np.concatenate([s[split] - quarter_s, s[split] + quarter_s, s[split] - quarter_s, s[split] + quarter_s])
        t = np.concatenate([t[split] - quarter_t, t[split] - quarter_t, t[split] + quarter_t, t[split] + quarter_t])
        ds, dt = np.tile(ds[split] / 2, 4), np.tile(dt[split] / 2, 4)
    centres = np.concatenate([d[0] for d in done])
    areas = np.concatenate([d[1] for d in done])
    return centres, np.broadcast_to(normal, centres.shape).copy(), areas


class Occluders:
    """The scene's planar rectangles as occluders of the segments between points: a segment is blocked where it
    crosses a rectangle strictly between its ends (curved surfaces do not occlude)."""

    def __init__(self, scene: Scene):
        self.planes = []
        for surface in scene.surfaces:
            if isinstance(surface, Rectangle):
                c, u, v = (np.asarray(x, dtype=np.float64) for x in (surface.centre, surface.half_u, surface.half_v))
                n = np.cross(u, v)
                self.planes.append((c, n / np.linalg.norm(n), u / (u @ u), v / (v @ v)))

    def visible(self, p: NDArray, q: NDArray) -> NDArray[np.bool_]:
        """Whether each point p (n, 3) [m] sees each point q (m, 3) [m] (n, m)."""
        clear = np.ones((p.shape[0], q.shape[0]), dtype=bool)
        for c, n, u, v in self.planes:
            dp, dq = (p - c) @ n, (q - c) @ n
            side_p = np.where(np.abs(dp) > ON_PLANE_M, np.sign(dp), 0.0)
            side_q = np.where(np.abs(dq) > ON_PLANE_M, np.sign(dq), 0.0)
            if not (side_p.max() * side_q.min() < 0 or side_p.min() * side_q.max() < 0):
                continue  # every point on one side of this plane: it blocks nothing
            # Single precision suffices: the crossing point is needed to a fraction of a patch.
            crosses = side_p[:, None] * side_q[None] < 0
            dp32, dq32 = dp.astype(np.float32), dq.astype(np.float32)
            blocked = crosses
            with np.errstate(invalid="ignore", divide="ignore"):  # pairs on the plane: they do not cross it
                t = dp32[:, None] / (dp32[:, None] - dq32[None])
                for axis in (u, v):
                    pa, qa = ((p - c) @ axis).astype(np.float32), ((q - c) @ axis).astype(np.float32)
                    blocked &= np.abs(pa[:, None] + t * (qa[None] - pa[:, None])) <= 1.0
            clear &= ~blocked
        return clear


def _facing(points: NDArray, normals: NDArray, patches: Patches) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Distance r (n, m) [m], cos_A, cos_B and the mask of point-patch pairs that face each other."""
    r, cos_a, cos_b = pair_geometry(points[:, None, :], normals[:, None, :], patches.centres[None],
                                    patches.normals[None])
    cos_b = np.where(patches.two_sided[None], np.abs(cos_b), cos_b)
    return r, cos_a, cos_b, (cos_a > 0) & (cos_b > 0)


def phase_columns(length_m: NDArray, wavenumbers: NDArray) -> NDArray[np.complex64]:
    """e^{j k s} (..., K) of path lengths s (...) [m] per wavenumber k (K,) [rad/m], in single precision.

    Where the wavenumbers are small multiples of a common one (the sensor's frequencies are 2, 3, 4 and 5 times
    6.25 MHz), one complex exponential and its powers replace one per wavenumber.
    """
    positive = wavenumbers > 0
    harmonics = harmonic_multiples(wavenumbers[positive]) if positive.any() else None
    if harmonics is None:
        return np.exp(1j * (length_m[..., None] * wavenumbers).astype(np.float32))
    base_k, positive_multiples = harmonics
    multiples = np.zeros(wavenumbers.size, dtype=np.int64)  # k = 0: the power 0, a phasor of 1
    multiples[positive] = positive_multiples
    base = np.exp(1j * (base_k * length_m).astype(np.float32))
    powers = [np.ones_like(base)]
    for _ in range(int(multiples.max())):
        powers.append(powers[-1] * base)
    return np.stack([powers[m] for m in multiples], axis=-1)


def transfer_powers(patches: Patches, occluders: Occluders, wavenumbers: NDArray, bounces: int) -> NDArray:
    """S = T + T^2 + ... + T^(bounces - 1) (K, M, M) per wavenumber (K,) [rad/m] (k = 0: real), of the
    patch-to-patch transfer T_jk (module docstring) with its phase, each patch's outgoing share held at most
    its albedo."""
    r, cos_j, cos_k, facing = _facing(patches.centres, patches.normals, patches)
    cos_j = np.where(patches.two_sided[:, None], np.abs(cos_j), cos_j)
    facing = (cos_j > 0) & (cos_k > 0) & (patches.surface[:, None] != patches.surface[None])
    facing &= occluders.visible(patches.centres, patches.centres)
    clamp = np.maximum(patches.clamp_m[:, None], patches.clamp_m[None])
    share = np.where(facing, cos_j * cos_k * patches.areas[None] / (np.pi * np.maximum(r, clamp) ** 2), 0.0)
    share /= np.maximum(share.sum(1, keepdims=True), 1.0)  # patch j cannot send on more than all its light
    transfer = (patches.albedo[:, None] * share).astype(np.float32)[None] * phase_columns(r, wavenumbers
                                                                                           ).transpose(2, 0, 1)
    total, power = transfer.copy(), transfer
    for _ in range(bounces - 2):
        power = power @ transfer
        total += power
    return total


@dataclass(frozen=True)
class MultiBounce:
    """What :func:`multibounce_ratios` found for some pixels (n,): the multipath ratio Gamma_M / Gamma_D of the
    single bounces per partner surface and wavenumber (n, S, K) and of the higher bounces per wavenumber (n, K),
    the single bounces' summed ratio per partner surface (n, S) and that ratio times their half extra path (n, S)
    [m], and the single-bounce white coupling kappa (n,) [1] before the cap."""

    single: NDArray[np.complex128]
    higher: NDArray[np.complex128]
    single_magnitude: NDArray[np.float64]
    single_moment_m: NDArray[np.float64]
    kappa: NDArray[np.float64]


def multibounce_ratios(scene: Scene, points: NDArray, normals: NDArray, which: NDArray, cos_i: NDArray,
                       area_m2: float, near: Patches, far: Patches | None, transfer: NDArray | None,
                       occluders: Occluders, wavenumbers: NDArray) -> MultiBounce:
    """The multipath of pixels (n,): points (n, 3) [m] with sensor-facing normals (n, 3) on surfaces ``which``
    (n,) hit at incidence cos_i (n,), for the effective footprint ``area_m2`` [m^2] and wavenumbers (K,)
    [rad/m]; single bounces over the ``near`` patches, higher ones over the ``far`` patches and their summed
    ``transfer`` (:func:`transfer_powers`; None: single bounces only)."""
    albedo_a = np.array([s.albedo for s in scene.surfaces])[which]
    cos_i = np.maximum(cos_i, 1e-3)
    r, cos_a, cos_b, facing = _facing(points, normals, near)
    facing &= (near.surface[None] != which[:, None]) & occluders.visible(points, near.centres)
    clamped = np.maximum(r, near.clamp_m[None])
    kappa_b = np.where(facing, (cos_a * cos_b) ** 2 * near.areas[None] * area_m2
                       / (np.pi**2 * clamped**4 * cos_i[:, None]), 0.0)  # physics.coupling's kernel, white
    ratio = kappa_b * albedo_a[:, None] * near.albedo[None]
    # One column per partner surface: the sums over its patches are one product.
    partner = (near.surface[:, None] == np.arange(len(scene.surfaces))[None]).astype(np.float32)
    weighted = ratio.astype(np.float32)[:, :, None] * phase_columns(2 * r, wavenumbers)  # eq 15: d_AS + r
    single = (weighted.transpose(0, 2, 1) @ partner).transpose(0, 2, 1).astype(np.complex128)
    higher = np.zeros((points.shape[0], wavenumbers.size), dtype=np.complex128)
    if far is not None and transfer is not None:
        higher = _higher_bounces(points, normals, which, albedo_a, cos_i, area_m2, far, transfer, occluders,
                                 wavenumbers)
    return MultiBounce(single, higher, ratio @ partner, (ratio * r) @ partner, kappa_b.sum(1))


def _higher_bounces(points: NDArray, normals: NDArray, which: NDArray, albedo_a: NDArray, cos_i: NDArray,
                    area_m2: float, far: Patches, transfer: NDArray, occluders: Occluders,
                    wavenumbers: NDArray) -> NDArray[np.complex128]:
    """out T^(n-1) back / cos_i summed over n = 2 .. bounces (n, K) (module docstring)."""
    r, cos_a, cos_b, facing = _facing(points, normals, far)
    facing &= (far.surface[None] != which[:, None]) & occluders.visible(points, far.centres)
    geometry = np.where(facing, cos_a * cos_b / (np.pi * np.maximum(r, far.clamp_m[None]) ** 2), 0.0)
    out_share = geometry * far.areas[None]
    out_share /= np.maximum(out_share.sum(1, keepdims=True), 1.0)  # A cannot send on more than all its light
    out = (albedo_a[:, None] * out_share).astype(np.float32)
    back = (geometry * far.albedo[None] * area_m2 / cos_i[:, None]).astype(np.float32)
    phase = phase_columns(r, wavenumbers).transpose(2, 0, 1)  # (K, n, M)
    through = (out[None] * phase) @ transfer  # (K, n, M)
    return np.einsum("knj,knj->nk", through, back[None] * phase).astype(np.complex128)


def multibounce_transport(scene: Scene, config: Config, footprint_radius_m: float, patch_spacing_m: float,
                          coupling_gain: float = 1.0, coupling_out: dict[str, NDArray] | None = None, *,
                          bounces: int = DEFAULT_BOUNCES, grading_m: float | None = GRADING_M,
                          ) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
    """:func:`~mpi_lidar.simulation.scenes.light_transport` with up to ``bounces`` bounces and occlusion.

    Returns the phasor (H*W, F) [V^2] and the DC sum of path amplitudes (H*W, F) [V^2]. ``coupling_out``
    receives what :func:`light_transport` gives (``coupling`` the single-bounce white kappa after the cap,
    ``rho_aba`` and ``d_ab_m`` of all the multipath: its summed magnitude over a cos_i and its magnitude-weighted
    half extra path length [m], ``bias_m``), and ``single_ratio`` (H*W, S, F), the single-bounce multipath ratio
    per partner surface, and ``higher_ratio`` (H*W, F), that of the higher bounces, both after the cap.
    ``grading_m`` None: uniform patches, with which ``bounces`` = 1 is the single-bounce transport, occlusion
    aside.
    """
    s = config.sensor
    c = s.speed_of_light_m_per_s
    freqs = np.asarray(config.frequencies_hz, dtype=np.float64)
    wavenumbers = np.concatenate([2 * np.pi * freqs / c, [0.0]])  # the sensor's frequencies, then the DC sum
    rays = grid_rays(scene.azimuth_rad, scene.elevation_rad).reshape(-1, 3)
    d_as, which = first_hits(scene)
    n, f = rays.shape[0], freqs.size
    occluders = Occluders(scene)
    near = scene_patches(scene, patch_spacing_m, grading_m)
    far, transfer = None, None
    if bounces > 1:
        far = scene_patches(scene, COARSE_FACTOR * patch_spacing_m, None if grading_m is None else COARSE_GRADING_M)
        transfer = transfer_powers(far, occluders, wavenumbers, bounces)
    area_m2 = footprint_area(footprint_radius_m, coupling_gain)
    surfaces = len(scene.surfaces)
    single = np.zeros((n, surfaces, f + 1), dtype=np.complex128)
    higher = np.zeros((n, f + 1), dtype=np.complex128)
    magnitude, moment = np.zeros((n, surfaces)), np.zeros((n, surfaces))
    kappa, gamma_d, cos_i_all = np.zeros(n), np.zeros(n), np.ones(n)
    for _, surface, block, points, normals, cos_i in surface_hits(scene, rays, d_as, which, PIXEL_BLOCK):
        found = multibounce_ratios(scene, points, normals, which[block], cos_i, area_m2, near, far, transfer,
                                   occluders, wavenumbers)
        single[block], higher[block], kappa[block] = found.single, found.higher, found.kappa
        magnitude[block], moment[block] = found.single_magnitude, found.single_moment_m
        gamma_d[block] = s.gamma_r_v2 * surface.albedo * cos_i / d_as[block] ** 2  # eq 12
        cos_i_all[block] = cos_i
    # Energy: A cannot get back more than all its light through B (kappa <= 1, as in the prior).
    scale = 1.0 / np.maximum(kappa, 1.0)
    single *= scale[:, None, None]
    higher *= scale[:, None]
    multipath = single.sum(1) + higher  # (n, F + 1): the sensor's frequencies, then the DC sum
    both_paths = 1 + multipath[:, :f]
    hit = which >= 0
    direct = np.zeros((n, f), dtype=np.complex128)
    direct[hit] = path_phasor(gamma_d[hit, None], d_as[hit, None], freqs[None, :], c)  # eq 12, 14
    dc_ratio = multipath[:, f].real
    if coupling_out is not None:
        coupling_out.update(_truth(scene, which, cos_i_all, scale, dc_ratio, magnitude, moment, higher, freqs, c))
        coupling_out.update(coupling=kappa * scale, single_ratio=single[:, :, :f], higher_ratio=higher[:, :f],
                            bias_m=np.where(hit[:, None], np.angle(both_paths) * c / (4 * np.pi * freqs), np.nan))
    return direct * both_paths, np.repeat((gamma_d * (1 + dc_ratio))[:, None], f, axis=1)


def _truth(scene: Scene, which: NDArray, cos_i: NDArray, scale: NDArray, dc_ratio: NDArray, magnitude: NDArray,
           moment: NDArray, higher: NDArray, freqs: NDArray, c: float) -> dict[str, NDArray]:
    """The render's true rho_ABA (the summed multipath magnitude over a cos_i) and d_AB [m] (its magnitude-weighted
    half extra path: the single bounces' exactly, the higher bounces' from their phase at the lowest frequency)."""
    hit = which >= 0
    albedo = np.where(hit, np.array([s.albedo for s in scene.surfaces] + [np.nan])[which], np.nan)
    lowest = int(np.argmin(freqs))
    higher_length = np.mod(np.angle(higher[:, lowest]), 2 * np.pi) * c / (4 * np.pi * freqs[lowest])
    weighted = scale * (moment.sum(1) + np.abs(higher[:, lowest]) * higher_length)
    weight = scale * magnitude.sum(1) + np.abs(higher[:, lowest])
    with np.errstate(invalid="ignore", divide="ignore"):
        return {"rho_aba": np.where(hit, dc_ratio / (albedo * cos_i), 0.0),
                "d_ab_m": np.where(weight > 0, weighted / weight, np.nan)}
