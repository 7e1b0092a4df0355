"""Where the self-calibrated footprint errs as the multipath grows: each suspect taken out alone.

Run: .venv/bin/python -m benchmarks.calibration_diagnosis [--quick] [--seed 1]
Renders corners at several true footprints A_fp and prints, per corner, the ratio estimate / truth of:

1. ``shipped``: :func:`mpi_lidar.correction.footprint.estimate_footprint` as correction runs it (the flat
   surfaces as planes continued beyond the view);
2. ``amplitude alone``: the footprint the amplitude tells, which the shipped estimate joins with the depth's
   (the same model fitted to the amplitude, one albedo per surface eliminated, started from the depth's
   estimate);
3. ``true albedo``: the shipped estimate with each surface's true albedo instead of its amplitude's;
4. ``exact, planes``: the same planes fit, its multipath model worked out per pixel from the exact surfaces
   in the field of view only (true planes, true albedo, the renderer's 2 cm clamp);
5. ``exact, reference``: that exact model against the reference depth, without planes.

A ``*`` marks a significant estimate: rows 4 and 5 on the depth alone, row 2 on its statistical
uncertainty alone. ``--quick`` runs one corner at two footprints on fewer pixels (for a test).
"""

from __future__ import annotations

import argparse
import platform
from datetime import date
from unittest import mock

import numpy as np
from numpy.typing import NDArray

from benchmarks.calibration import coupling_gain
from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction import footprint
from mpi_lidar.correction.footprint import _albedo, _estimate
from mpi_lidar.correction.footprint._fit import FootprintFit
from mpi_lidar.physics.coupling import footprint_coupling, pair_geometry
from mpi_lidar.physics.noise import depth_noise_m
from mpi_lidar.scans import geometry
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation.scenes import DEFAULT_PATCH_SPACING_M, corner, render

CORNERS = ((60, 2.4, 0.9), (90, 1.4, 0.9))
FOOTPRINTS_M2 = (0.004, 0.016, 0.041, 0.1)
VARIANTS = ("shipped", "amplitude alone", "true albedo", "exact, planes", "exact, reference")
PARTNER_STEP = 2  # every second pixel of the partner surface along each axis is a patch


def corner_normals(angle_deg: float) -> tuple[NDArray, NDArray]:
    """Unit normals (towards the scanner) of the left (x < 0) and right boards of :func:`corner`."""
    half = np.deg2rad(angle_deg) / 2
    return np.array([np.cos(half), 0.0, -np.sin(half)]), np.array([-np.cos(half), 0.0, -np.sin(half)])


def exact_unit_phasors(scan: Scan, angle_deg: float, albedo: float, pixels: NDArray, c: float
                       ) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
    """The unit-footprint multipath phasor (n, F) and white coupling (n,) of flat pixels, summed over the
    other board's pixels in the field of view on the true surfaces (every :data:`PARTNER_STEP`-th one)."""
    rays = scan.rays()
    reference = scan.reference_depth.astype(np.float64)
    points = (reference[..., None] * rays).reshape(-1, 3)
    right = points[:, 0] > 0
    left_normal, right_normal = corner_normals(angle_deg)
    normals = np.where(right[:, None], right_normal, left_normal)
    cos_i = np.abs(np.einsum("ni,ni->n", rays.reshape(-1, 3), normals))
    area = (reference**2 * geometry.pixel_solid_angle(rays)).ravel() / np.maximum(cos_i, 0.1) * PARTNER_STEP**2
    sampled = np.zeros(reference.shape, dtype=bool)
    sampled[::PARTNER_STEP, ::PARTNER_STEP] = True
    patch = sampled.ravel() & np.isfinite(reference).ravel()
    freqs = np.asarray(scan.frequencies_hz)
    phasor = np.zeros((pixels.size, freqs.size), dtype=np.complex128)
    kappa = np.zeros(pixels.size)
    for rows in np.array_split(np.arange(pixels.size), max(1, pixels.size // 200)):
        for side in (False, True):
            chosen = rows[right[pixels[rows]] == side]
            at, partners = pixels[chosen], np.flatnonzero(patch & (right != side))
            r, cos_a, cos_b = pair_geometry(points[at][:, None], normals[at][:, None], points[partners][None],
                                            normals[partners][None])
            weight = footprint_coupling(cos_a, cos_b, area[partners][None], np.maximum(r, DEFAULT_PATCH_SPACING_M),
                                        np.maximum(cos_i[at], 1e-3)[:, None], 1.0)
            weight = np.where((cos_a > 0) & (cos_b > 0), weight, 0.0)
            kappa[chosen] = weight.sum(1)
            wave = np.exp(1j * 4 * np.pi * freqs[None, None] * r[..., None] / c)
            phasor[chosen] = albedo**2 * np.einsum("nm,nmf->nf", weight, wave)
    return phasor, kappa


def exact_estimates(scan: Scan, blocks: geometry.FacingBlocks, valid: NDArray, sensor: SensorConfig,
                    angle_deg: float, albedo: float, max_pixels: int) -> tuple:
    """Rows 3 and 4: the planes fit and the reference fit with the exact per-pixel model."""
    labels = footprint.surface_labels(blocks).flat
    unit_coupling = np.bincount(blocks.index[blocks.pairs.a], blocks.pairs.kappa(1.0), minlength=blocks.usable.size)
    pixels = _estimate._fit_pixels(blocks, labels, unit_coupling, valid, max_pixels)
    pixels = pixels[np.isfinite(scan.reference_depth.ravel()[pixels])]
    ys, xs = np.divmod(pixels, blocks.shape[1])
    depth = scan.depth[:, ys, xs].astype(np.float64).T
    amplitude = scan.amplitude[:, ys, xs].astype(np.float64).T
    metres_per_rad = sensor.speed_of_light_m_per_s / (4 * np.pi * np.asarray(scan.frequencies_hz))
    sigma = np.maximum(depth_noise_m(sensor, scan.frequencies_hz, amplitude), 1e-5)
    surface = labels[(ys // blocks.block_pixels) * blocks.usable.shape[1] + xs // blocks.block_pixels]
    phasor, kappa = exact_unit_phasors(scan, angle_deg, albedo, pixels, sensor.speed_of_light_m_per_s)
    arguments = (depth, sigma, phasor, kappa, metres_per_rad, amplitude / sensor.gamma_r_v2, scan.pixel_rays(ys, xs),
                 surface)
    planes = FootprintFit(*arguments, None).solve(footprint.EstimateMethod.PLANES, with_amplitude=False)
    reference = FootprintFit(*arguments, scan.reference_depth.ravel()[pixels].astype(np.float64))
    return planes, reference.solve(footprint.EstimateMethod.REFERENCE, with_amplitude=False)


def diagnose(angle: float, distance: float, albedo: float, true_m2: float, seed: int, max_pixels: int
             ) -> dict[str, footprint.FootprintEstimate]:
    """The four estimates of one rendered corner."""
    config = Config()
    scan = render(corner(angle, distance, albedo), config, np.random.default_rng(seed),
                  coupling_gain=coupling_gain(true_m2))
    valid = np.isfinite(scan.depth[-1])
    blocks = geometry.facing_blocks(np.where(valid, scan.depth[-1], np.nan), scan.ray_rows())
    amplitude_fits: list[footprint.FootprintEstimate] = []
    fit_amplitude = FootprintFit._fit_amplitude

    def kept_amplitude_fit(fit: FootprintFit, method: footprint.EstimateMethod, **options: float
                           ) -> footprint.FootprintEstimate:
        found = fit_amplitude(fit, method, **options)
        amplitude_fits.append(found)
        return found

    with mock.patch.object(FootprintFit, "_fit_amplitude", kept_amplitude_fit):
        found = {"shipped": footprint.estimate_footprint(scan, blocks, valid.ravel(), config.sensor,
                                                         max_pixels=max_pixels)}
    found["amplitude alone"] = amplitude_fits[-1] if amplitude_fits else footprint.NOTHING_MEASURED
    true_albedo = lambda measured, components, coupling: np.where(measured > 0, albedo, 0.0)  # noqa: E731
    with mock.patch.object(_albedo, "surface_albedo", true_albedo):
        found["true albedo"] = footprint.estimate_footprint(scan, blocks, valid.ravel(), config.sensor,
                                                            max_pixels=max_pixels)
    found["exact, planes"], found["exact, reference"] = exact_estimates(scan, blocks, valid.ravel(), config.sensor,
                                                                        angle, albedo, max_pixels)
    return found


def cell(estimate: footprint.FootprintEstimate, true_m2: float) -> str:
    return f"{estimate.area_m2 / true_m2:.2f}{'*' if estimate.significant else ''}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="One corner at two footprints, fewer pixels.")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    corners, footprints = (CORNERS[:1], FOOTPRINTS_M2[1::2]) if args.quick else (CORNERS, FOOTPRINTS_M2)
    max_pixels = 2_000 if args.quick else _estimate.MAX_FIT_PIXELS
    print(f"Machine: {platform.node()} ({platform.machine()}), {date.today()}; seed {args.seed}\n")
    for angle, distance, albedo in corners:
        print(f"Corner {angle} deg, {distance} m, albedo {albedo}: estimate / true footprint\n")
        print("| variant | " + " | ".join(f"{a:g} m^2" for a in footprints) + " |")
        print("|---|" + "---|" * len(footprints))
        found = [diagnose(angle, distance, albedo, a, args.seed, max_pixels) for a in footprints]
        for variant in VARIANTS:
            print(f"| {variant} | " + " | ".join(cell(f[variant], a) for f, a in zip(found, footprints, strict=True))
                  + " |", flush=True)
        print()


if __name__ == "__main__":
    main()
