"""Correction per corner strength: room corners and strong two-plane corners, against the truth of the render.

Run: .venv/bin/python -m benchmarks.corner_strength --model DIR [--seed 0] [--shrink 1] [--renderer mitsuba]
     [--only TEXT]
 or: .venv/bin/python -m benchmarks.corner_strength --partners  (the partners' light summed or the dominant one's)

Renders the rooms of :func:`benchmarks.scenes.room_set` (two walls and a floor, a 0.35 m box, 48 x 64 pixels; the
turned room with a ceiling, 72 x 96; multi-bounce light transport with occlusion) at each footprint, and the 60-
and 90-degree corners at 0.073 m^2, at Table I noise, and corrects each with default options (the scan's own
footprint) and with the true footprint given (``footprint_area_m2``). Per scene it prints the MAE of the 31.25 MHz
depth and of the output [mm] on the reference mask, within 20 cm of the folds (a corner's edge; a room's folds,
box and floor included) and within 20 cm of a room's tri-corners; the same with the true footprint; the noise
floor (the default correction of the same scan rendered without multipath, same noise); the model's lower bound,
fed the render's exact inputs (every pixel whose true bias reaches 2 mm corrected by the model with the rho_ABA
and d_AB (F15) of the render's own multipath ratio at the lowest frequency, the others as the default run left
them); the footprint estimated
against the true one; the share of corrected pixels whose geometric inputs lie beyond the model's training prior
(its card's rho_ABA and d_AB ranges); the share of valid pixels within their 1-sigma uncertainty; and the pixels
made worse by more than three times their noise (|output - reference| > |true multipath bias| + 3 sigma, sigma
the 31.25 MHz noise). A second table splits each default run's masked pixels into those the model corrected and
those it left alone: their count, share of the error, MAE, mean error, coverage and share with a true bias above
the gate's 4 mm.

With ``--renderer mitsuba`` the same scenes are path traced by Mitsuba 3 instead (:mod:`benchmarks.mitsuba_render`:
``--samples`` paths per pixel, up to ten bounces; the scans carry its Monte Carlo noise, about 0.2 mm of bias at
32,768 paths), so the check does not share the project renderer's light-transport kernel.
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import date

import numpy as np
from numpy.typing import NDArray

from benchmarks.scenes import (
    EDGE_RADIUS_M,
    ROOM_FOOTPRINTS_M2,
    ROOMS,
    covered_share,
    edge_line,
    edge_line_region,
    mae_mm,
    valid_pixels,
)
from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, correct_scan
from mpi_lidar.correction.options import Estimate
from mpi_lidar.correction.result import Correction
from mpi_lidar.learning.features import geometry_inputs
from mpi_lidar.learning.model import CorrectionModel, load_model
from mpi_lidar.physics.coupling import DEFAULT_COUPLING_GAIN
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation.scenes import (
    Scene,
    corner,
    first_hits,
    light_transport,
    scan_from_phasors,
    simple_region_mask,
)

STRONG_CORNER_M2 = 0.073
# The pixels whose true multipath bias reaches this [m] get the model fed the render's exact inputs in the lower
# bound (the gate's default threshold).
TRUE_INPUTS_MIN_BIAS_M = 2e-3


@dataclass(frozen=True)
class Case:
    """A scene to render at the effective footprint ``footprint_m2`` [m^2]."""

    label: str
    scene: Callable[[], Scene]
    footprint_m2: float


def cases(shrink: int = 1) -> list[Case]:
    """The rooms at each of ROOM_FOOTPRINTS_M2, then the strong 60- and 90-degree corners."""
    found = []
    for (_, factory, (height, width)), short in zip(ROOMS, ("room", "turned room"), strict=True):
        for area in ROOM_FOOTPRINTS_M2:
            found.append(Case(f"{short}, {area:g} m^2",
                              lambda f=factory, h=height, w=width: f(height=h // shrink, width=w // shrink), area))
    for angle in (60.0, 90.0):
        found.append(Case(f"corner {angle:g} deg, {STRONG_CORNER_M2:g} m^2",
                          lambda a=angle: corner(a, 2.0, 0.8, 96 // shrink, 128 // shrink), STRONG_CORNER_M2))
    return found


@dataclass(frozen=True)
class Rendered:
    """A case rendered twice with the same noise: with its multipath (``scan``) and without (``direct``), the true
    multipath bias of the 31.25 MHz depth (H, W) [m] and the regions (H, W): near a fold, near a tri-corner."""

    scan: Scan
    direct: Scan
    true_bias_m: NDArray[np.float64]
    folds: NDArray[np.bool_]
    tri_corners: NDArray[np.bool_]
    exact_inputs: NDArray[np.float64]
    # The multipath ratio at the lowest frequency (H*W, 2): the single bounces and the higher ones; path traced,
    # all the light in the first and NaN in the second (the tracer does not split it).
    true_light: NDArray[np.complex128] | None = None


def exact_inputs(phasor: NDArray, direct: NDArray, ranges_m: NDArray, config: Config) -> NDArray[np.float64]:
    """The geometric inputs (n, 2) a render's own light gives its pixels, from their phasors (n, F) with all the
    light and with the direct return alone and their ranges (n,) [m]: (F15) of the true multipath ratio at the
    lowest frequency, rho_ABA = |ratio| / (rho_A cos_i) and d_AB its phase over the wavenumber [m], rho_A cos_i
    read off the direct return (Gamma_R rho_A cos_i / d^2); 0 where the direct return is nothing."""
    lowest = int(np.argmin(config.frequencies_hz))
    ratio = lowest_ratio(phasor, direct, config)
    with np.errstate(divide="ignore", invalid="ignore"):
        albedo_cos = np.abs(direct[:, lowest]) * ranges_m**2 / config.sensor.gamma_r_v2
        rho_aba = np.abs(ratio) / albedo_cos
    wavenumber = 4 * np.pi * config.frequencies_hz[lowest] / config.sensor.speed_of_light_m_per_s
    d_ab = np.mod(np.angle(ratio), 2 * np.pi) / wavenumber
    return geometry_inputs(np.where(np.isfinite(rho_aba), rho_aba, 0.0), np.where(np.isfinite(d_ab), d_ab, 0.0))


def lowest_ratio(phasor: NDArray, direct: NDArray, config: Config) -> NDArray[np.complex128]:
    """The multipath ratio (n,) at the lowest frequency of phasors (n, F) with all the light and with the direct
    return alone (NaN where the direct return is nothing)."""
    lowest = int(np.argmin(config.frequencies_hz))
    with np.errstate(divide="ignore", invalid="ignore"):
        return phasor[:, lowest] / direct[:, lowest] - 1.0


def render_case(case: Case, config: Config, rng_seed: list[int]) -> Rendered:
    """Render ``case`` with and without its multipath through :func:`scan_from_phasors` (the same noise)."""
    scene = case.scene()
    radius = float(np.sqrt(case.footprint_m2 / (DEFAULT_COUPLING_GAIN * np.pi)))
    truth: dict[str, NDArray] = {}
    spacing = float(scene.notes.get("patch_spacing_m", 0.02))
    phasor, dc = light_transport(scene, config, radius, spacing, DEFAULT_COUPLING_GAIN, truth)
    h, w = scene.elevation_rad.size, scene.azimuth_rad.size
    d_as, which = first_hits(scene)
    reference = np.where(np.isfinite(d_as), d_as, np.nan).reshape(h, w).astype(np.float32)
    extras = {"azimuth_rad": scene.azimuth_rad, "elevation_rad": scene.elevation_rad, "reference_depth": reference,
              "reference_mask": simple_region_mask(scene, which.reshape(h, w))}
    f = len(config.frequencies_hz)
    if "single_ratio" in truth:  # multi-bounce: the phasor over 1 + its multipath ratio is the direct path
        direct = phasor / (1.0 + truth["single_ratio"].sum(1) + truth["higher_ratio"])
    else:
        direct, _ = light_transport(scene, config, radius, spacing, 0.0)
    scans = [scan_from_phasors(scene.name, p.T.reshape(f, h, w), config, np.random.default_rng(rng_seed),
                               dc_gamma=d, **extras) for p, d in ((phasor, dc.T.reshape(f, h, w)), (direct, None))]
    points = reference[..., None] * scans[0].rays()
    folds = _near_segments(points, scene.folds) if scene.folds else edge_line_region(scans[0], edge_line(2.0))
    tri = _near_points(points, scene.tri_corners)
    lowest = int(np.argmin(config.frequencies_hz))
    light = (np.column_stack([truth["single_ratio"][:, :, lowest].sum(1), truth["higher_ratio"][:, lowest]])
             if "single_ratio" in truth else np.column_stack([lowest_ratio(phasor, direct, config), np.zeros(h * w)]))
    return Rendered(scans[0], scans[1], truth["bias_m"][:, -1].reshape(h, w), folds, tri,
                    exact_inputs(phasor, direct, d_as, config), light)


def path_traced_case(case: Case, config: Config, rng_seed: list[int], samples: int) -> Rendered:
    """Render ``case`` with Mitsuba's path tracer (:func:`benchmarks.mitsuba_render.path_trace`), with and without
    its multipath, through the sensor model with the same noise."""
    from benchmarks.mitsuba_render import path_trace, scan_of, true_bias_m

    scene = case.scene()
    paths_seed = 1_000_003 * (rng_seed[-1] + 101 * rng_seed[0])  # the case and --seed
    traced = path_trace(scene, config, case.footprint_m2, samples=samples, seed=paths_seed)
    scan, direct = (scan_of(scene, traced, config, np.random.default_rng(rng_seed), direct_only=alone)
                    for alone in (False, True))
    assert scan.reference_depth is not None
    points = scan.reference_depth[..., None] * scan.rays()
    folds = _near_segments(points, scene.folds) if scene.folds else edge_line_region(scan, edge_line(2.0))
    f = len(config.frequencies_hz)
    phasor, alone = traced.phasor.reshape(f, -1).T, traced.direct.reshape(f, -1).T
    inputs = exact_inputs(phasor, alone, scan.reference_depth.ravel().astype(np.float64), config)
    light = np.column_stack([lowest_ratio(phasor, alone, config), np.full(phasor.shape[0], np.nan)])
    return Rendered(scan, direct, true_bias_m(traced, config), folds, _near_points(points, scene.tri_corners),
                    inputs, light)


def _near_segments(points: NDArray, segments: tuple) -> NDArray[np.bool_]:
    """Points (H, W, 3) [m] within EDGE_RADIUS_M of any of the segments ((a, b), ...) [m]."""
    near = np.zeros(points.shape[:2], dtype=bool)
    for a, b in segments:
        a, b = np.asarray(a), np.asarray(b)
        along = np.clip(((points - a) @ (b - a)) / ((b - a) @ (b - a)), 0.0, 1.0)
        near |= np.linalg.norm(points - (a + along[..., None] * (b - a)), axis=-1) <= EDGE_RADIUS_M
    return near


def _near_points(points: NDArray, corners: tuple) -> NDArray[np.bool_]:
    """Points (H, W, 3) [m] within EDGE_RADIUS_M of any of ``corners`` [m]."""
    near = np.zeros(points.shape[:2], dtype=bool)
    for corner_point in corners:
        near |= np.linalg.norm(points - np.asarray(corner_point), axis=-1) <= EDGE_RADIUS_M
    return near


@dataclass(frozen=True)
class Row:
    """One case's figures: MAE [mm] per region (masked, folds, tri-corners) as (raw, default, true footprint,
    true inputs, noise floor); the footprint estimate and its sd [m^2] (NaN: not significant); the shares [1] of
    corrected pixels beyond the prior, of valid pixels within 1 sigma and of pixels made worse by > 3 sigma, and
    the count of the last."""

    mae_mm: dict[str, tuple[float, float, float, float, float]]
    footprint_m2: tuple[float, float]
    beyond_prior: float
    covered: float
    worse: float
    worse_pixels: int
    split: dict[str, Split]


@dataclass(frozen=True)
class Split:
    """The default run's masked pixels of one kind (corrected, or left alone: fused or measured): how many, their
    share of the masked error [1], MAE and mean signed error [mm], the share within 1 sigma [1] and the share whose
    true multipath bias exceeds the gate's 4 mm [1]."""

    pixels: int
    error_share: float
    mae_mm: float
    mean_mm: float
    covered: float
    biased: float


def measure(case: Case, rendered: Rendered, model: CorrectionModel, config: Config) -> Row:
    """Correct ``rendered`` with default options and with the true footprint, and its multipath-free twin."""
    scan = rendered.scan
    assert scan.reference_depth is not None and scan.reference_mask is not None
    default = correct_scan(scan, model)
    given = correct_scan(scan, model, CorrectionOptions(footprint_area_m2=case.footprint_m2))
    floor = correct_scan(rendered.direct, model)
    usable = valid_pixels(scan, default) & valid_pixels(scan, given) & valid_pixels(rendered.direct, floor)
    reference = scan.reference_depth
    regions = {"masked": usable & scan.reference_mask, "folds": usable & rendered.folds,
               "tri-corners": usable & rendered.tri_corners}
    exact = _exact_inputs_depth(scan, default, model, rendered)
    mae = {name: (mae_mm(scan.depth[-1], reference, where), mae_mm(default.depth, reference, where),
                  mae_mm(given.depth, reference, where), mae_mm(exact, reference, where),
                  mae_mm(floor.depth, reference, where))
           for name, where in regions.items()}
    worse = _made_worse(scan, default, rendered.true_bias_m, config) & usable
    return Row(mae, _footprint(default), _beyond_prior_share(default), covered_share(default, reference, usable),
               float(worse.sum() / max(usable.sum(), 1)), int(worse.sum()),
               _split(default, reference, regions["masked"], rendered.true_bias_m))


def _exact_inputs_depth(scan: Scan, run: Correction, model: CorrectionModel, rendered: Rendered) -> NDArray:
    """The model's lower bound (H, W) [m]: every pixel whose true bias reaches TRUE_INPUTS_MIN_BIAS_M corrected by
    the model fed the render's exact inputs, the others as ``run`` left them."""
    depth = run.depth.astype(np.float64).ravel()
    strong = (np.abs(np.nan_to_num(rendered.true_bias_m.ravel())) >= TRUE_INPUTS_MIN_BIAS_M) & np.isfinite(depth)
    depth[strong] = model.predict_depth(scan.raw_pixels()[strong], rendered.exact_inputs[strong])
    return depth.reshape(scan.shape)


def _split(run: Correction, reference: NDArray, where: NDArray, true_bias_m: NDArray) -> dict[str, Split]:
    """The masked pixels ``where`` split into those the model corrected and those it left alone."""
    assert run.estimate is not None
    error = run.depth.astype(np.float64) - reference
    total = max(float(np.abs(error[where]).sum()), 1e-300)
    corrected = run.estimate.reshape(where.shape) == Estimate.CORRECTED
    found = {}
    for name, kind in (("corrected", corrected), ("left alone", ~corrected)):
        pixels = where & kind
        if not pixels.any():
            continue
        found[name] = Split(int(pixels.sum()), float(np.abs(error[pixels]).sum() / total),
                            1e3 * float(np.abs(error[pixels]).mean()), 1e3 * float(error[pixels].mean()),
                            covered_share(run, reference, pixels), float((np.abs(true_bias_m[pixels]) > 4e-3).mean()))
    return found


def _made_worse(scan: Scan, run: Correction, true_bias_m: NDArray, config: Config) -> NDArray[np.bool_]:
    """Pixels whose output error exceeds the true multipath bias by more than 3 sigma of the 31.25 MHz noise."""
    noise = NoiseModel.for_sensor(config.sensor, scan.frequencies_hz)
    f = len(scan.frequencies_hz)
    amplitude = np.asarray(scan.amplitude, dtype=np.float64).reshape(f, -1).T
    sigma = noise.depth_sigma_m(amplitude)[:, -1].reshape(scan.shape)
    assert scan.reference_depth is not None
    error = np.abs(run.depth.astype(np.float64) - scan.reference_depth)
    with np.errstate(invalid="ignore"):
        return error > np.abs(true_bias_m) + 3 * sigma


def _footprint(run: Correction) -> tuple[float, float]:
    estimate = run.calibration
    if estimate is None or not estimate.significant:
        return float("nan"), float("nan")
    return estimate.area_m2, estimate.sigma_m2


def _beyond_prior_share(run: Correction) -> float:
    corrected = run.estimate_counts().get(Estimate.CORRECTED.name.lower(), 0)
    return run.beyond_prior_pixels / corrected if corrected else float("nan")


HEADER = ("| scene | masked, raw -> default / true footprint / true inputs / noise floor [mm] | folds, the same [mm] "
          "| tri-corners, the same [mm] | footprint estimated [m^2] | corrected beyond the prior | within 1 sigma "
          "| made worse by > 3 sigma |\n|---|---|---|---|---|---|---|---|")


def format_row(case: Case, row: Row) -> str:
    cells = [" / ".join(_mm(v) for v in values[1:]) if np.isfinite(values[0]) else ""
             for values in row.mae_mm.values()]
    cells = [f"{_mm(values[0])} -> {cell}" if cell else "" for values, cell in zip(row.mae_mm.values(), cells,
                                                                                  strict=True)]
    area, sd = row.footprint_m2
    footprint = (f"{area:.3f} +- {sd:.3f} ({area / case.footprint_m2:.2f}x)" if np.isfinite(area)
                 else "not significant")
    return (f"| {case.label} | {' | '.join(cells)} | {footprint} | {100 * row.beyond_prior:.1f} % "
            f"| {100 * row.covered:.1f} % | {row.worse_pixels} ({100 * row.worse:.2f} %) |")


SPLIT_HEADER = ("| scene | pixels | share of the masked error | MAE [mm] | mean error [mm] | within 1 sigma "
                "| true bias > 4 mm |\n|---|---|---|---|---|---|---|")


def format_split(case: Case, row: Row) -> str:
    """The default run's corrected and left-alone masked pixels of one case, "corrected / left alone" per cell."""
    parts = [row.split.get(name) for name in ("corrected", "left alone")]

    def cell(text: Callable[[Split], str]) -> str:
        return " / ".join(text(part) if part is not None else "-" for part in parts)

    return (f"| {case.label} | {cell(lambda p: str(p.pixels))} | {cell(lambda p: f'{100 * p.error_share:.0f} %')} "
            f"| {cell(lambda p: f'{p.mae_mm:.2f}')} | {cell(lambda p: f'{p.mean_mm:+.2f}')} "
            f"| {cell(lambda p: f'{100 * p.covered:.0f} %')} | {cell(lambda p: f'{100 * p.biased:.0f} %')} |")


def _mm(value: float) -> str:
    return f"{value:.2f}" if np.isfinite(value) else "-"


def partner_rows(shrink: int, config: Config) -> None:
    """--partners: per room and footprint, the MAE [mm] of the 31.25 MHz bias one two-path term predicts against
    the render's true bias (every bounce), the term fitted at the lowest frequency to: the sum of all the light,
    the sum of the single bounces (what the geometry stage models), the dominant partner's single bounces."""
    print("| room | pixels (facing two surfaces) | mean true bias [mm] | all light summed [mm] | single bounces "
          "summed [mm] | dominant partner alone [mm] |\n|---|---|---|---|---|---|")
    wavenumbers = 2 * np.pi * np.asarray(config.frequencies_hz) / config.sensor.speed_of_light_m_per_s
    for case in cases(shrink)[:2 * len(ROOM_FOOTPRINTS_M2)]:
        truth: dict[str, NDArray] = {}
        radius = float(np.sqrt(case.footprint_m2 / (DEFAULT_COUPLING_GAIN * np.pi)))
        light_transport(case.scene(), config, radius, 0.03, DEFAULT_COUPLING_GAIN, truth)
        single, true = truth["single_ratio"], truth["bias_m"][:, -1]
        where = np.isfinite(true) & (np.abs(true) > 1e-3)
        magnitude = np.abs(single[:, :, 0])
        two = where & ((magnitude > 0.2 * magnitude.max(1, keepdims=True)).sum(1) >= 2)
        dominant = np.take_along_axis(single, magnitude.argmax(1)[:, None, None], 1)[:, 0]
        cells = []
        for ratio in (single.sum(1) + truth["higher_ratio"], single.sum(1), dominant):
            low = ratio[:, 0]  # one path through the lowest frequency's phasor
            path = np.abs(low)[:, None] * np.exp(2j * wavenumbers * (np.mod(np.angle(low), 2 * np.pi)
                                                                      / (2 * wavenumbers[0]))[:, None])
            error = np.abs(np.angle(1 + path[:, -1]) / (2 * wavenumbers[-1]) - true)
            cells.append(f"{1e3 * error[where].mean():.2f} ({1e3 * error[two].mean():.2f})")
        print(f"| {case.label} | {where.sum()} ({two.sum()}) | {1e3 * np.abs(true[where]).mean():.2f} | "
              + " | ".join(cells) + " |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--shrink", type=int, default=1, help="Divide every scene's height and width by this.")
    parser.add_argument("--renderer", choices=("project", "mitsuba"), default="project",
                        help="Render with the project's renderer or path trace with Mitsuba 3 (the render group).")
    parser.add_argument("--samples", type=int, default=32768, help="Paths per pixel with --renderer mitsuba.")
    parser.add_argument("--only", default="", help="Only the scenes whose label contains this text.")
    parser.add_argument("--partners", action="store_true",
                        help="Only compare the partners' light summed with the dominant partner's (no model).")
    args = parser.parse_args()
    started = time.perf_counter()
    config = Config()
    if args.partners:
        partner_rows(args.shrink, config)
        return
    if not args.model:
        parser.error("give --model (or --partners)")
    model = load_model(args.model)
    reach = model.card.dataset.prior.multipath_reach()
    prior = f"rho_ABA <= {reach[0]:g}, d_AB <= {reach[1]:g} m" if reach else "its reach not on the card"
    renderer = ("the project's renderer" if args.renderer == "project"
                else f"Mitsuba 3 path traced, {args.samples} paths per pixel")
    print(f"model {args.model} ({model.booster.num_boosted_rounds()} trees, prior {prior}); default options, "
          f"Table I noise, seed {args.seed}; {renderer}\n")
    print(HEADER)
    measured = []
    for index, case in enumerate(cases(args.shrink)):
        if args.only not in case.label:
            continue
        rendered = (render_case(case, config, [args.seed, index]) if args.renderer == "project"
                    else path_traced_case(case, config, [args.seed, index], args.samples))
        measured.append((case, measure(case, rendered, model, config)))
        print(format_row(*measured[-1]), flush=True)
    print("\nWhere the error sits: the default run's masked pixels, corrected / left alone (fused or measured)\n")
    print(SPLIT_HEADER)
    for case, row in measured:
        print(format_split(case, row))
    print(f"\n{platform.system()}, {platform.machine()}, Python {platform.python_version()}, {date.today()}, "
          f"{time.perf_counter() - started:.0f} s wall")


if __name__ == "__main__":
    main()
