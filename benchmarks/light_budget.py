"""The geometry stage's light budget: the multipath its partner planes predict against the render's own.

Run: .venv/bin/python -m benchmarks.light_budget [--seed 0] [--shrink 1] [--only TEXT] [--renderer mitsuba
     --samples 8192]

Renders the scenes of :mod:`benchmarks.corner_strength` with the project's renderer (the rooms with up to three
bounces and occlusion, the strong corners) at Table I noise and runs the correction's stages up to the scene
geometry with the true footprint given, so that only the light model is measured, not the footprint's estimate.
For every pixel whose true 31.25 MHz bias reaches 2 mm and that a partner plane lights, it compares the multipath
ratio at the lowest frequency the stage predicts (:meth:`PlaneModelInputs.light_parts`) with the render's, as the
median of |predicted| / |true| per pixel: all the light, the single bounces, and the higher bounces (the light
among the partners, the rooms only), within 20 cm of a fold and further away; and the true share of the light in
the higher bounces. A ratio under 1 is light the model's inputs leave out: the model then under-corrects.

With ``--renderer mitsuba`` the scenes are path traced by Mitsuba 3 instead (:mod:`benchmarks.mitsuba_render`,
up to ten bounces, the receiver's footprint a disc): all the light only, as the tracer does not split it.
"""

from __future__ import annotations

import argparse
import platform
import time
from dataclasses import dataclass
from datetime import date

import numpy as np
from numpy.typing import NDArray

from benchmarks.corner_strength import (
    TRUE_INPUTS_MIN_BIAS_M,
    Case,
    Rendered,
    cases,
    path_traced_case,
    render_case,
)
from mpi_lidar.config import Config
from mpi_lidar.correction.options import CorrectionOptions
from mpi_lidar.correction.scene import analyse_geometry
from mpi_lidar.correction.sensor_reading import read_sensor
from mpi_lidar.correction.tiles import in_v2, scan_tiles
from mpi_lidar.correction.validity import check_validity

HEADER = ("| scene | pixels, near folds / away | all light, predicted / true: near / away | single bounces, the same "
          "| higher bounces, the same | rho_ABA, the same | true share in higher bounces |\n"
          "|---|---|---|---|---|---|---|")


@dataclass(frozen=True)
class Budget:
    """The pixels a budget is over: their ratios at the lowest frequency (n, 2), predicted and true, in single
    bounces and higher ones; their rho_ABA (n, 2) [1], the stage's and the render's exact one; and whether each
    lies near a fold (n,)."""

    predicted: NDArray[np.complex128]
    true: NDArray[np.complex128]
    rho_aba: NDArray[np.float64]
    near_fold: NDArray[np.bool_]

    def rho_aba_ratio(self, near: bool) -> float:
        """Median of the stage's rho_ABA over the render's, near the folds or away."""
        where = (self.near_fold == near) & (self.rho_aba[:, 1] > 0)
        return float(np.median(self.rho_aba[where, 0] / self.rho_aba[where, 1])) if where.any() else float("nan")

    @property
    def split(self) -> bool:
        """Whether the render split its light into single and higher bounces."""
        return not np.isnan(self.true[:, 1]).any()

    def ratio(self, part: int | None, near: bool) -> float:
        """Median |predicted| / |true| of one part (0 single, 1 higher, None both) near the folds or away."""
        where = self.near_fold == near
        true_parts = np.nan_to_num(self.true[where])
        if part is None:
            predicted, true = self.predicted[where].sum(1), true_parts.sum(1)
        else:
            predicted, true = self.predicted[where, part], true_parts[:, part]
        lit = np.abs(true) > 0
        return float(np.median(np.abs(predicted[lit]) / np.abs(true[lit]))) if lit.any() else float("nan")

    def higher_share(self) -> float:
        """Median share of the true light's magnitude in the higher bounces (NaN where not split)."""
        total = np.abs(self.true.sum(1))
        return float(np.median(np.abs(self.true[:, 1]) / total)) if total.size and self.split else float("nan")


def light_budget(case: Case, rendered: Rendered, config: Config) -> Budget:
    """The stages of the correction up to the scene geometry on ``rendered``, its true footprint given."""
    assert rendered.true_light is not None, "a render of the project's renderer"
    options = CorrectionOptions(footprint_area_m2=case.footprint_m2)
    reading = read_sensor(rendered.scan, config.sensor, options)
    validity = check_validity(in_v2(rendered.scan, reading.units_per_v2), reading.noise, options,
                              scan_tiles(rendered.scan, options.tile_pixels), None, reading.saturation_v2)
    scene = analyse_geometry(validity.scan, validity.usable_depth, options, config.sensor, with_model_inputs=True,
                             noise=reading.noise)
    strong = np.abs(np.nan_to_num(rendered.true_bias_m.ravel())) >= TRUE_INPUTS_MIN_BIAS_M
    pixels = np.flatnonzero(strong & np.isfinite(validity.usable_depth))
    if scene.model_inputs is None:
        pixels = pixels[:0]
    measured_range = validity.usable_depth[pixels].astype(np.float64)
    single, among = (np.zeros((2, 0), dtype=np.complex128) if scene.model_inputs is None
                     else scene.model_inputs.light_parts(pixels, measured_range))
    lit = np.abs(single + among) > 0
    pixels = pixels[lit]
    rho_aba = (np.zeros(0) if scene.model_inputs is None
               else scene.model_inputs.pixels(pixels, measured_range[lit])[0])
    return Budget(np.column_stack([single[lit], among[lit]]), rendered.true_light[pixels],
                  np.column_stack([rho_aba, rendered.exact_inputs[pixels, 0]]), rendered.folds.ravel()[pixels])


def format_row(case: Case, budget: Budget) -> str:
    near = int(budget.near_fold.sum())

    def pair(part: int | None) -> str:
        return " / ".join(_ratio(budget.ratio(part, side)) for side in (True, False))

    single = pair(0) if budget.split else "-"
    higher = pair(1) if budget.split and np.abs(budget.true[:, 1]).any() else "-"
    rho_aba = " / ".join(_ratio(budget.rho_aba_ratio(side)) for side in (True, False))
    return (f"| {case.label} | {near} / {budget.near_fold.size - near} | {pair(None)} | {single} | {higher} | "
            f"{rho_aba} | {_share(budget.higher_share())} |")


def _ratio(value: float) -> str:
    return f"{value:.2f}" if np.isfinite(value) else "-"


def _share(value: float) -> str:
    return f"{value:.0%}" if np.isfinite(value) else "-"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--shrink", type=int, default=1, help="Divide every scene's height and width by this.")
    parser.add_argument("--only", default="", help="Only the scenes whose label contains this text.")
    parser.add_argument("--renderer", choices=("project", "mitsuba"), default="project",
                        help="Render with the project's renderer or path trace with Mitsuba 3 (the render group).")
    parser.add_argument("--samples", type=int, default=8192, help="Paths per pixel with --renderer mitsuba.")
    args = parser.parse_args()
    started = time.perf_counter()
    config = Config()
    renderer = ("the project's renderer" if args.renderer == "project"
                else f"Mitsuba 3 path traced, {args.samples} paths per pixel")
    print(f"{renderer}, Table I noise, seed {args.seed}; true footprint given; pixels of a true bias "
          f">= {TRUE_INPUTS_MIN_BIAS_M * 1e3:g} mm a partner plane lights\n")
    print(HEADER)
    for index, case in enumerate(cases(args.shrink)):
        if args.only in case.label:
            rendered = (render_case(case, config, [args.seed, index]) if args.renderer == "project"
                        else path_traced_case(case, config, [args.seed, index], args.samples))
            print(format_row(case, light_budget(case, rendered, config)), flush=True)
    print(f"\n{platform.system()}, {platform.machine()}, Python {platform.python_version()}, {date.today()}, "
          f"{time.perf_counter() - started:.0f} s wall")


if __name__ == "__main__":
    main()
