"""Mixed pixels at depth edges: a plate before a wall, rendered with sub-ray footprints, through the correction.

Run: .venv/bin/python -m benchmarks.mixed_pixels [--model DIR] [--work DIR] [--quick] [--per-scene]
[--scene TEXT ...] [--no-clean]

The scenes: the issue's three, a sweep of gaps (0.2-10 m) and albedo pairs (0.05-20) with the plate at 2 m, the
plate at 1, 5 and 10 m with gaps of 0.2-5 m, and the plate at 2 and 5 m with its right edge turned 30 or 45 degrees
from the vertical, or seen with footprints twice the pixels' pitch (two pixels in a row straddle its edge). Each is
a fronto-parallel plate before a fronto-parallel wall, both Lambertian, seen on a small scan grid; each pixel's
footprint is 4 x 4 sub-rays per pitch it spans, each hitting the plate (inside a rectangle whose edges fall between
pixel centres, or that rectangle with its right edge turned) or the wall, and the pixel's phasor at each frequency is
the sum of its sub-rays' (amplitude Gamma_R albedo cos / r^2, phase 4 pi f r / c), through the sensor model with its
noise (:func:`mpi_lidar.simulation.scenes.scan_from_phasors`). A mixed pixel is one whose sub-rays hit both. The
scans are corrected with default options (:func:`mpi_lidar.correction.correct_scan`) and the benchmark prints, per
group of scenes (the edge straight, or turned / wide; the plate's range; the plate darker than, as bright as or
brighter than the wall), or per scene with ``--per-scene``:

- the mixed pixels, and of them: reported as one valid depth (not resolved) more than 5 cm from both surfaces (the
  target: at most 2 %), of those the ones also more than 3 times their own uncertainty (the depth's 1-sigma) from
  both, and how many a clean pixel of the same uncertainty would put more than 5 cm off (the sum of
  erfc(5 cm / (sqrt(2) sigma)): the share of the misses the noise alone explains); the earlier count beside them,
  which also took in the resolved pixels whose stronger return (their corrected depth) lies that far; flagged
  ``mixed``, resolved (``two_returns``), flagged ``inconsistent``;
- of the resolved, judged by their own target: those in its domain (a gap of 2 m or more, the weaker return
  holding 20 % of the light or more; of the mixed pixels there), and the share of those whose nearer and farther
  return lie within 3 times their two-return Cramer-Rao bound at the truth; the share of all resolved returns within
  their stated 1-sigma (the corrected depth's uncertainty, the second return's ``sigma_m``; about 68 % where the
  stated sigma is right); the nearer and the farther return's median and largest error against the plate's and the
  wall's range (per scene only), and the median of those errors over the bound;
- the share of the pixels of one surface whose valid depth lies more than 5 cm from it: where it is not near 0 the
  5 cm criterion lies within the noise, and mixed pixels miss it as often for that reason;
- per group, also the worst scene's share of single depths more than 5 cm off, and the range of its scenes' median
  error over the bound;
- then the share of pixels flagged mixed or two_returns on clean surfaces (flat walls, corners, the cornered board,
  1-20 m; the target: under 0.1 %), per kind of surface (per scan with ``--per-scene``).

The model is ``--model DIR``, or one trained here as the correction benchmark's (``--quick``: a small one and a
smaller sweep). ``--scene TEXT`` keeps the plate scenes whose label (as the per-scene table writes it) holds TEXT,
each with the seed it has in the whole run; ``--no-clean`` leaves the clean scenes out.
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.special import erfc

from benchmarks.correction import trained_model
from mpi_lidar.config import Config
from mpi_lidar.correction import INVALID_FLAGS, Correction, CorrectionOptions, Flag, correct_scan
from mpi_lidar.correction._mixed_bounds import range_sigmas
from mpi_lidar.learning.model import CorrectionModel, load_model
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation.scenes import corner, cornered_board, flat_wall, render, scan_from_phasors

SUB = 4  # sub-rays per pixel pitch, along each side of a footprint
NOISE_SIGMAS = 3.0  # a flying point in units of the noise: this many of its uncertainty from both surfaces
# The resolution target's domain: a gap of 2 m or more, the weaker return holding 20 % of the light or more; there
# both ranges lie within 3 times their two-return Cramer-Rao bound.
DOMAIN_GAP_M = 2.0
DOMAIN_SHARE = 0.2
DOMAIN_BOUNDS = 3.0
HEIGHT, WIDTH = 48, 64
HALF_FOV_RAD = 0.12


@dataclass(frozen=True)
class PlateScene:
    """A plate of ``plate_albedo`` at ``plate_m`` before a wall of ``wall_albedo`` at ``wall_m``; its right edge
    turned ``edge_deg`` from the vertical, each pixel's footprint ``footprint`` times the pixels' pitch wide."""

    plate_m: float
    plate_albedo: float
    wall_m: float
    wall_albedo: float
    edge_deg: float = 0.0
    footprint: int = 1

    @property
    def label(self) -> str:
        shape = "".join((f", edge {self.edge_deg:g} deg" if self.edge_deg else "",
                         f", footprint {self.footprint} px" if self.footprint > 1 else ""))
        return f"{self.plate_albedo:g} at {self.plate_m:g} m{shape} | {self.wall_albedo:g} at {self.wall_m:g} m"


ISSUE_SCENES = (PlateScene(1.5, 0.05, 3.0, 1.0), PlateScene(1.5, 0.9, 3.0, 0.3), PlateScene(2.0, 0.1, 9.0, 1.0))


def sweep(quick: bool) -> tuple[PlateScene, ...]:
    """Gaps 0.2-10 m and albedo ratios 0.05-20 (plate over wall), plate at 2 m."""
    gaps = (0.2, 1.0, 3.0, 10.0) if quick else (0.2, 0.5, 1.0, 2.0, 3.0, 5.0, 10.0)
    pairs = ((0.05, 1.0), (1.0, 0.05)) if quick else ((0.05, 1.0), (0.2, 0.8), (0.5, 0.5), (0.8, 0.2), (1.0, 0.05))
    return tuple(PlateScene(2.0, p, 2.0 + g, wa) for g in gaps for p, wa in pairs)


def range_sweep(quick: bool) -> tuple[PlateScene, ...]:
    """The plate at 1, 5 and 10 m: gaps 0.2-5 m, the two extreme albedo ratios and equal albedos."""
    ranges, gaps = ((5.0,), (0.2, 2.0)) if quick else ((1.0, 5.0, 10.0), (0.2, 0.5, 2.0, 5.0))
    pairs = ((0.5, 0.5),) if quick else ((0.05, 1.0), (0.5, 0.5), (1.0, 0.05))
    return tuple(PlateScene(r, p, r + g, wa) for r in ranges for g in gaps for p, wa in pairs)


def edge_sweep(quick: bool) -> tuple[PlateScene, ...]:
    """Diagonal edges (30 and 45 degrees) and footprints twice the pitch: the plate at 2 and 5 m, gaps of 0.5 and
    2 m, a dark plate before a bright wall and equal albedos."""
    shapes = ((45.0, 1), (0.0, 2)) if quick else ((30.0, 1), (45.0, 1), (0.0, 2), (30.0, 2), (45.0, 2))
    ranges, gaps = ((5.0,), (0.5,)) if quick else ((2.0, 5.0), (0.5, 2.0))
    pairs = ((0.5, 0.5),) if quick else ((0.05, 1.0), (0.5, 0.5))
    return tuple(PlateScene(r, p, r + g, wa, edge, footprint) for edge, footprint in shapes for r in ranges
                 for g in gaps for p, wa in pairs)


@dataclass(frozen=True)
class Truth:
    """Per pixel (H, W): the plate's and the wall's range [m] and the plate's share of the sub-rays [1]."""

    plate_m: NDArray[np.float64]
    wall_m: NDArray[np.float64]
    plate_share: NDArray[np.float64]
    plate_light: NDArray[np.float64]  # the plate's share of the light


def render_plate(scene: PlateScene, config: Config, rng: np.random.Generator) -> tuple[Scan, Truth]:
    """The scene's scan (sub-ray footprints, the sensor's noise) and its truth per pixel."""
    az = np.linspace(-HALF_FOV_RAD, HALF_FOV_RAD, WIDTH)
    el = np.linspace(-HALF_FOV_RAD * HEIGHT / WIDTH, HALF_FOV_RAD * HEIGHT / WIDTH, HEIGHT)
    step = az[1] - az[0]
    sub = SUB * scene.footprint
    offsets = scene.footprint * ((np.arange(sub) + 0.5) / sub - 0.5)
    sub_az = (az[None, :, None, None] + step * offsets[None, None, None, :])  # (1, W, 1, sub)
    sub_el = (el[:, None, None, None] + step * offsets[None, None, :, None])  # (H, 1, sub, 1)
    tan_x, tan_y = np.tan(sub_az), np.tan(sub_el)
    # The plate: a rectangle in angle, left part of the view; its right edge turned about its middle by edge_deg,
    # and moved half a pitch per pitch the footprint spans beyond one, so that a footprint two pitches wide sees it
    # in two pixels of a row.
    edge_rad = 0.0133 + (scene.footprint - 1) * step / 2
    right = np.tan(edge_rad) + np.tan(np.deg2rad(scene.edge_deg)) * (tan_y - np.tan(-0.0039))
    on_plate = (tan_x < right) & (tan_y > np.tan(-0.0571)) & (tan_y < np.tan(0.0493))
    on_plate = np.broadcast_to(on_plate, (HEIGHT, WIDTH, sub, sub))
    cosine = 1.0 / np.sqrt(1.0 + tan_x**2 + tan_y**2)  # incidence on a fronto-parallel plane
    freqs = np.asarray(config.frequencies_hz)
    c = config.sensor.speed_of_light_m_per_s
    phasor = np.zeros((freqs.size, HEIGHT, WIDTH), np.complex128)
    light = {}
    for name, depth, albedo, where in (("plate", scene.plate_m, scene.plate_albedo, on_plate),
                                       ("wall", scene.wall_m, scene.wall_albedo, ~on_plate)):
        r = depth / cosine
        amp = np.where(where, config.sensor.gamma_r_v2 * albedo * cosine / r**2, 0.0) / sub**2
        light[name] = amp.sum(axis=(2, 3))
        for k, f in enumerate(freqs):
            phasor[k] += (amp * np.exp(1j * 4 * np.pi * f * r / c)).sum(axis=(2, 3))
    centre = 1.0 / np.sqrt(1.0 + np.tan(az)[None, :] ** 2 + np.tan(el)[:, None] ** 2)
    truth = Truth(scene.plate_m / centre, scene.wall_m / centre, on_plate.mean(axis=(2, 3)),
                  light["plate"] / (light["plate"] + light["wall"]))
    scan = scan_from_phasors(f"plate-{scene.plate_m:g}-{scene.wall_m:g}", phasor, config, rng,
                             azimuth_rad=az, elevation_rad=el)
    return scan, truth


@dataclass(frozen=True)
class SceneResult:
    mixed: int
    single_far: int  # unresolved, reported as one valid depth > 5 cm from both surfaces: the target's count
    single_far_noise: int  # ...and more than 3 of its own uncertainty from both
    surface_far: float  # the share of the valid pixels of one surface > 5 cm from it: the criterion's noise floor
    flagged: int
    resolved: int
    inconsistent: int
    near_errors: NDArray[np.float64]  # of the resolved pixels' nearer return, against the plate [m]
    far_errors: NDArray[np.float64]  # ...and of the farther, against the wall [m]
    crb_ratios: NDArray[np.float64]
    far_resolved: int = 0  # resolved pixels whose stronger return (the corrected depth) lies > 5 cm from both
    noise_expected: float = 0.0  # of the unresolved valid ones, how many a clean pixel's noise puts > 5 cm off
    domain_mixed: int = 0  # mixed pixels in the resolution target's domain: gap >= 2 m, weaker >= 20 % of the light
    domain_resolved: int = 0  # ...of them resolved
    near_within: int = 0  # ...of those, the nearer return within DOMAIN_BOUNDS of its Cramer-Rao bound
    far_within: int = 0  # ...and the farther
    stated_covered: int = 0  # resolved returns (two a pixel) within their stated 1-sigma

    @property
    def earlier_count(self) -> int:
        """The earlier definition's count: valid depths > 5 cm from both surfaces, resolved pixels by their
        stronger return."""
        return self.single_far + self.far_resolved


def crb_m(near: NDArray, far: NDArray, a_near: NDArray, a_far: NDArray, noise: NoiseModel) -> NDArray[np.float64]:
    """The two-return Cramer-Rao bound (k, 2) [m] of the near and far range, real amplitudes, at the truth."""
    freqs = np.asarray(noise.frequencies_hz)
    c = noise.speed_of_light_m_per_s
    w = 4 * np.pi * freqs / c
    light = np.abs(a_near[:, None] * np.exp(1j * w * near[:, None]) + a_far[:, None] * np.exp(1j * w * far[:, None]))
    return range_sigmas(near, far, a_near, a_far, freqs, noise.quadrature_sigma_v2(light), c)


def evaluate(scene: PlateScene, model: CorrectionModel, config: Config, seed: int) -> SceneResult:
    scan, truth = render_plate(scene, config, np.random.default_rng(seed))
    corrected = correct_scan(scan, model, CorrectionOptions(), config.sensor)
    mixed = (truth.plate_share > 0) & (truth.plate_share < 1)
    flags, depth = corrected.flags, corrected.depth
    valid = ~np.isin(flags, [int(f) for f in INVALID_FLAGS]) & np.isfinite(depth)
    off = np.minimum(np.abs(depth - truth.plate_m), np.abs(depth - truth.wall_m))
    far = off > 0.05
    sigma = corrected.uncertainty_m if corrected.uncertainty_m is not None else np.zeros_like(depth)
    far_noise = far & (off > NOISE_SIGMAS * np.nan_to_num(sigma, nan=0.0))
    own = np.where(truth.plate_share == 1, truth.plate_m, truth.wall_m)
    surface = ~mixed & valid
    resolved = mixed & (flags == Flag.TWO_RETURNS)
    single = mixed & valid & ~resolved
    noise_expected = float(erfc(0.05 / (np.sqrt(2) * np.maximum(np.nan_to_num(sigma[single], nan=0.0), 1e-9))).sum())
    weaker_light = np.minimum(truth.plate_light, 1 - truth.plate_light)
    domain = mixed & (scene.wall_m - scene.plate_m >= DOMAIN_GAP_M) & (weaker_light >= DOMAIN_SHARE)
    returns = resolved_returns(scene, truth, corrected, resolved, domain[resolved], config)
    return SceneResult(int(mixed.sum()), int((single & far).sum()), int((single & far_noise).sum()),
                       float((np.abs(depth - own)[surface] > 0.05).mean()), int((mixed & (flags == Flag.MIXED)).sum()),
                       int(resolved.sum()), int((mixed & (flags == Flag.INCONSISTENT)).sum()), *returns[:3],
                       far_resolved=int((resolved & far).sum()), noise_expected=noise_expected,
                       domain_mixed=int(domain.sum()), domain_resolved=int((domain & resolved).sum()),
                       near_within=returns[3], far_within=returns[4], stated_covered=returns[5])


def resolved_returns(scene: PlateScene, truth: Truth, corrected: Correction, resolved: NDArray,
                     in_domain: NDArray, config: Config) -> tuple[NDArray, NDArray, NDArray, int, int, int]:
    """The resolved pixels' nearer and farther return's errors against the plate and the wall [m], both over their
    Cramer-Rao bound at the truth; of those ``in_domain`` (one per resolved pixel), how many nearer and farther
    returns lie within ``DOMAIN_BOUNDS`` bounds; and how many returns lie within their stated 1-sigma."""
    # The two returns by range, the nearer against the plate: which of them is the stronger is a coin's toss
    # where they are about equally bright, and not what is measured here.
    second = corrected.second_returns
    if second is None or not resolved.any():
        return np.zeros(0), np.zeros(0), np.zeros(0), 0, 0, 0
    depth, other = corrected.depth[resolved], second.depth_m[resolved]
    near_err = np.abs(np.minimum(depth, other) - truth.plate_m[resolved])
    far_err = np.abs(np.maximum(depth, other) - truth.wall_m[resolved])
    noise = NoiseModel.for_sensor(config.sensor, config.frequencies_hz)
    total = np.abs(scan_light(truth, scene, config))[resolved]
    a_plate, a_wall = total * truth.plate_light[resolved], total * (1 - truth.plate_light[resolved])
    bound = crb_m(truth.plate_m[resolved], truth.wall_m[resolved], a_plate, a_wall, noise)
    near_ratio, far_ratio = near_err / bound[:, 0], far_err / bound[:, 1]
    stated = (np.full(depth.shape, np.nan) if corrected.uncertainty_m is None else corrected.uncertainty_m[resolved],
              np.full(depth.shape, np.nan) if second.sigma_m is None else second.sigma_m[resolved])
    depth_truth = np.where(depth <= other, truth.plate_m[resolved], truth.wall_m[resolved])
    other_truth = np.where(depth <= other, truth.wall_m[resolved], truth.plate_m[resolved])
    covered = int((np.abs(depth - depth_truth) < stated[0]).sum() + (np.abs(other - other_truth) < stated[1]).sum())
    return (near_err, far_err, np.concatenate([near_ratio, far_ratio]),
            int((near_ratio[in_domain] <= DOMAIN_BOUNDS).sum()), int((far_ratio[in_domain] <= DOMAIN_BOUNDS).sum()),
            covered)


def scan_light(truth: Truth, scene: PlateScene, config: Config) -> NDArray[np.float64]:
    """The two returns' summed amplitude per pixel (H, W) [V^2], from the shares (pixel-centre ranges)."""
    g = config.sensor.gamma_r_v2
    plate = g * scene.plate_albedo * truth.plate_share / truth.plate_m**2
    wall = g * scene.wall_albedo * (1 - truth.plate_share) / truth.wall_m**2
    return plate + wall


def clean_scans(config: Config, quick: bool) -> list[tuple[str, float | None, Scan]]:
    """Flat walls (square and turned 45 degrees), corners and the cornered board at 1-20 m: each scan with its
    kind and distance (None for the board)."""
    distances = (1.0, 5.0, 20.0) if quick else (1.0, 2.0, 5.0, 10.0, 20.0)
    board = render(cornered_board(60, 80), config, np.random.default_rng(1), patch_spacing_m=0.05)
    out: list[tuple[str, float | None, Scan]] = [("cornered board", None, board)]
    for i, d in enumerate(distances):
        for kind, scene in (("flat wall", flat_wall(0.0, d, height=60, width=80)),
                            ("flat wall 45 deg", flat_wall(45.0, d, height=60, width=80)),
                            ("corner", corner(90.0, d, height=60, width=80, board_m=0.3 * d,
                                              half_height_m=0.2 * d))):
            out.append((kind, d, render(scene, config, np.random.default_rng(10 + i), patch_spacing_m=0.05 * d)))
    return out


def false_flags(scan: Scan, model: CorrectionModel, config: Config) -> tuple[int, int]:
    """Pixels flagged mixed or two_returns, and pixels with a finite measured depth."""
    corrected = correct_scan(scan, model, CorrectionOptions(), config.sensor)
    flagged = np.isin(corrected.flags, [int(Flag.MIXED), int(Flag.TWO_RETURNS)])
    return int(flagged.sum()), int(np.isfinite(np.asarray(scan.depth[-1])).sum())


def _median(values: NDArray) -> str:
    return f"{np.median(values) * 1000:.1f}" if values.size else "-"


def _largest(values: NDArray) -> str:
    return f"{values.max() * 1000:.1f}" if values.size else "-"


def _percent(part: int, whole: int, digits: int = 0) -> str:
    return f"{100 * part / max(whole, 1):.{digits}f} %"


def all_scenes(quick: bool) -> tuple[PlateScene, ...]:
    return ISSUE_SCENES + sweep(quick) + range_sweep(quick) + edge_sweep(quick)


def _share(part: int, whole: int) -> str:
    return f"{100 * part / whole:.0f} %" if whole else "-"


def _resolved_cells(r: SceneResult | list[SceneResult]) -> str:
    """The resolved pixels' cells: in the domain (of the mixed pixels there), their nearer and farther returns
    within ``DOMAIN_BOUNDS`` bounds, all resolved returns within their stated 1-sigma."""
    rs = r if isinstance(r, list) else [r]
    domain, mixed = sum(x.domain_resolved for x in rs), sum(x.domain_mixed for x in rs)
    near, far = sum(x.near_within for x in rs), sum(x.far_within for x in rs)
    return (f"{domain} of {mixed} | {_share(near, domain)} / {_share(far, domain)} | "
            f"{_share(sum(x.stated_covered for x in rs), 2 * sum(x.resolved for x in rs))}")


PER_SCENE_HEADER = ("| plate | wall | mixed | single > 5 cm | single > 5 cm, 3 sigma | noise alone | earlier count | "
                    "flagged mixed | resolved | inconsistent | resolved in domain | near / far within 3 CRB | "
                    "within stated sigma | near error median / max [mm] | far error median / max [mm] | "
                    "error / CRB | surface > 5 cm |")


def per_scene_table(results: list[tuple[PlateScene, SceneResult]]) -> list[str]:
    lines = [PER_SCENE_HEADER, "|" + "---|" * 17]
    for scene, r in results:
        ratio = f"{np.median(r.crb_ratios):.2f}" if r.crb_ratios.size else "-"
        lines.append(f"| {scene.label} | {r.mixed} | {r.single_far} ({_percent(r.single_far, r.mixed)}) | "
                     f"{r.single_far_noise} | {r.noise_expected:.1f} | {r.earlier_count} | {r.flagged} | "
                     f"{r.resolved} | {r.inconsistent} | {_resolved_cells(r)} | "
                     f"{_median(r.near_errors)} / {_largest(r.near_errors)} | {_median(r.far_errors)} / "
                     f"{_largest(r.far_errors)} | {ratio} | {100 * r.surface_far:.0f} % |")
    return lines


def albedo_class(scene: PlateScene) -> str:
    if scene.plate_albedo == scene.wall_albedo:
        return "equal"
    return "darker plate" if scene.plate_albedo < scene.wall_albedo else "brighter plate"


def straight_edge(scene: PlateScene) -> bool:
    return scene.edge_deg == 0 and scene.footprint == 1


def scene_group(scene: PlateScene) -> str:
    """The summary row a scene counts in: its edge (straight, or turned / wide), plate range and albedo class."""
    edge = "straight" if straight_edge(scene) else "turned or wide"
    return f"{edge}, plate at {scene.plate_m:g} m, {albedo_class(scene)}"


def group_row(group: str, results: list[tuple[PlateScene, SceneResult]]) -> str:
    """One summary row: the group's sums, its worst scene's miss share, the range of its scenes' error / CRB."""
    rs = [r for _, r in results]
    mixed = sum(r.mixed for r in rs)
    single_far = sum(r.single_far for r in rs)
    worst_scene, worst = max(results, key=lambda sr: sr[1].single_far / max(sr[1].mixed, 1))
    worst_text = (f"{_percent(worst.single_far, worst.mixed, 1)} ({worst_scene.plate_albedo:g} / "
                  f"{worst_scene.wall_albedo:g}, gap {worst_scene.wall_m - worst_scene.plate_m:g} m)"
                  if worst.single_far else "-")
    ratios = [float(np.median(r.crb_ratios)) for r in rs if r.crb_ratios.size]
    ratio_text = "-" if not ratios else f"{min(ratios):.2f}" + (f"-{max(ratios):.2f}" if len(ratios) > 1 else "")
    earlier = sum(r.earlier_count for r in rs)
    return (f"| {group} | {len(results)} | {mixed} | {single_far} ({_percent(single_far, mixed, 1)}) | "
            f"{sum(r.single_far_noise for r in rs)} | {sum(r.noise_expected for r in rs):.1f} | {worst_text} | "
            f"{earlier} ({_percent(earlier, mixed, 1)}) | {sum(r.flagged for r in rs)} | "
            f"{sum(r.resolved for r in rs)} | {sum(r.inconsistent for r in rs)} | {_resolved_cells(rs)} | "
            f"{ratio_text} | {100 * max(r.surface_far for r in rs):.0f} % |")


SUMMARY_HEADER = ("| edge, plate range, albedos | scenes | mixed | single > 5 cm | single > 5 cm, 3 sigma | "
                  "noise alone | worst scene's single > 5 cm (plate / wall albedo, gap) | earlier count | "
                  "flagged mixed | resolved | inconsistent | resolved in domain | near / far within 3 CRB | "
                  "within stated sigma | error / CRB, scenes' medians | surface > 5 cm, worst |")


def summary_table(results: list[tuple[PlateScene, SceneResult]]) -> list[str]:
    """One row per edge shape, plate range and albedo class (plate darker than, as bright as, brighter than the
    wall): straight edges first, then by the plate's range; then a row of all."""
    groups: dict[str, list[tuple[PlateScene, SceneResult]]] = {}
    for scene, result in sorted(results, key=lambda sr: (not straight_edge(sr[0]), sr[0].plate_m)):
        groups.setdefault(scene_group(scene), []).append((scene, result))
    lines = [SUMMARY_HEADER, "|" + "---|" * 16]
    return lines + [group_row(group, members) for group, members in groups.items()] + [group_row("all", results)]


def clean_table(model: CorrectionModel, config: Config, quick: bool, per_scene: bool) -> list[str]:
    """Pixels flagged mixed or two_returns on clean scenes: per kind of scene (per scene with ``per_scene``)."""
    counts: dict[str, list[int]] = {}
    for kind, distance, scan in clean_scans(config, quick):
        row = kind if distance is None or not per_scene else f"{kind} {distance:g} m"
        flagged, measured = false_flags(scan, model, config)
        total = counts.setdefault(row, [0, 0])
        total[0], total[1] = total[0] + flagged, total[1] + measured
    counts["all"] = [sum(c[0] for c in counts.values()), sum(c[1] for c in counts.values())]
    lines = ["| clean scene | pixels flagged mixed or two_returns | pixels measured | share |", "|---|---|---|---|"]
    return lines + [f"| {row} | {flagged} | {measured} | {100 * flagged / max(measured, 1):.3f} % |"
                    for row, (flagged, measured) in counts.items()]


def report(model: CorrectionModel, quick: bool, per_scene: bool = False, only: tuple[str, ...] = (),
           clean: bool = True) -> str:
    """The plate scenes summarised per group (per scene with ``per_scene``), then the clean scenes' false flags;
    with ``only``, the plate scenes whose label holds one of its texts (each with its seed in the whole run), and
    without ``clean`` no clean scenes."""
    config = Config()
    results = [(scene, evaluate(scene, model, config, seed=100 + i)) for i, scene in enumerate(all_scenes(quick))
               if not only or any(text in scene.label for text in only)]
    table = per_scene_table(results) if per_scene else summary_table(results)
    return "\n".join([*table, *(["", *clean_table(model, config, quick, per_scene)] if clean else [])])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", type=Path, help="Model directory (default: train one here).")
    parser.add_argument("--work", type=Path, help="Where a trained model is kept (default: a temporary directory).")
    parser.add_argument("--quick", action="store_true", help="A small model and a smaller sweep.")
    parser.add_argument("--per-scene", action="store_true",
                        help="One row per scene and per clean scan (default: one per group of scenes).")
    parser.add_argument("--scene", action="append", default=[], metavar="TEXT",
                        help="Only the plate scenes whose label holds TEXT (repeatable; default: all).")
    parser.add_argument("--no-clean", action="store_true", help="Leave the clean scenes out.")
    args = parser.parse_args()
    labels = [scene.label for scene in all_scenes(args.quick)]
    unmatched = [text for text in args.scene if not any(text in label for label in labels)]
    if unmatched:
        parser.error(f"--scene {unmatched[0]!r} matches no plate scene; the labels are those of --per-scene's rows")
    work = args.work or Path(tempfile.mkdtemp(prefix="mixed-pixels-"))
    rows, rounds = (2_000, 10) if args.quick else (20_000, 100)
    model_dir = args.model or trained_model(work / f"model-{rows}-{rounds}", rows, rounds)
    print(report(load_model(model_dir), args.quick, args.per_scene, tuple(args.scene), not args.no_clean))


if __name__ == "__main__":
    main()
