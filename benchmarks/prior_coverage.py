"""Does the training prior cover the scenes? The geometry stage's per-pixel inputs where the gate asks for correction.

Run: .venv/bin/python -m benchmarks.prior_coverage [--seed 0] [--shrink 1] [--distances 0.5 1 2 4 8 12]
     [--rho-aba-max R --d-ab-max D]

Renders every corner of :func:`benchmarks.scenes.scene_set` (60-120 degrees, the cornered board, the wooden
corner), the two external corners, and corners of 60, 90 and 120 degrees at each of ``--distances`` (boards scaled
with the distance, so every one fills the view as the 2 m corner does), each at Table I noise. Each scan goes
through the correction's own stages with default options (the scan's own footprint): validity, the scene geometry
with a geometric model's inputs, the geometry gate. For the pixels the gate hands the model (flag CORRECTED) it
prints, per scene and over all of them, the quantiles (50, 90, 99, 99.9 %) of the equivalent rho_ABA [1], its d_AB
[m] and the coupling to a white partner [1], and the share of those pixels inside the prior (rho_ABA <= the
prior's largest, d_AB <= its largest): the ``wide`` preset's prior, the default configuration's (the paper's
multipath), and ``--rho-aba-max`` / ``--d-ab-max`` where given.
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import date
from functools import partial

import numpy as np
from numpy.typing import NDArray

from benchmarks.scenes import external_corner, scene_set
from mpi_lidar.config import Config, PriorConfig, preset
from mpi_lidar.correction.gates import make_gate
from mpi_lidar.correction.gating import decide
from mpi_lidar.correction.options import CorrectionOptions, Flag
from mpi_lidar.correction.scene import analyse_geometry
from mpi_lidar.correction.sensor_reading import read_sensor
from mpi_lidar.correction.tiles import in_v2, scan_tiles
from mpi_lidar.correction.validity import check_validity
from mpi_lidar.learning.features import geometry_inputs
from mpi_lidar.learning.model_card import PriorCard
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation.scenes import Scene, corner, render

QUANTILES = (0.5, 0.9, 0.99, 0.999)
DISTANCES_M = (0.5, 1.0, 2.0, 4.0, 8.0, 12.0)
ANGLES_DEG = (60.0, 90.0, 120.0)
# The scene set's corner boards at 2 m: 0.5 m from the edge, 0.35 m either side of the view's axis.
BOARD_M, HALF_HEIGHT_M, REFERENCE_DISTANCE_M = 0.5, 0.35, 2.0


@dataclass(frozen=True)
class GatedInputs:
    """The geometry stage's inputs of the pixels the gate hands the model: columns (n, 3) of the equivalent
    rho_ABA [1], its d_AB [m] and the coupling to a white partner [1]."""

    values: NDArray[np.float64]

    @property
    def rho_aba(self) -> NDArray[np.float64]:
        return self.values[:, 0]

    @property
    def d_ab_m(self) -> NDArray[np.float64]:
        return self.values[:, 1]

    def inside(self, reach: tuple[float, float]) -> float:
        """Share of the pixels inside a prior of largest rho_ABA and d_AB ``reach`` [1, m]. [1]"""
        if not self.values.shape[0]:
            return float("nan")
        return float(((self.rho_aba <= reach[0]) & (self.d_ab_m <= reach[1])).mean())


def gated_inputs(scan: Scan, config: Config, options: CorrectionOptions | None = None) -> GatedInputs:
    """Run the correction's stages up to the gate on ``scan`` and return the inputs of the pixels it corrects.

    The gate's range rule takes the default configuration's d_AS range; a geometric model is assumed (the inputs
    are worked out)."""
    options = options or CorrectionOptions()
    reading = read_sensor(scan, config.sensor, options)
    gate = make_gate(options)
    validity = check_validity(in_v2(scan, reading.units_per_v2), reading.noise, options,
                              scan_tiles(scan, options.tile_pixels), gate, reading.saturation_v2)
    scene = analyse_geometry(validity.scan, validity.usable_depth, options, config.sensor, with_model_inputs=True,
                             noise=reading.noise)
    decision = decide(validity, gate, scene, config.prior.d_as_m, options, geometric_model=True)
    pixels = np.flatnonzero(decision.flags == Flag.CORRECTED)
    if scene.model_inputs is None or scene.potential is None or not pixels.size:
        return GatedInputs(np.zeros((0, 3)))
    inputs = geometry_inputs(*scene.model_inputs.pixels(pixels, validity.usable_depth[pixels].astype(np.float64)))
    coupling = scene.potential.pixels(pixels).coupling
    return GatedInputs(np.column_stack([inputs, coupling]))


def scaled_corner(angle_deg: float, distance_m: float, shrink: int) -> Scene:
    """A corner of ``angle_deg`` whose edge is ``distance_m`` away, its boards scaled with the distance."""
    scale = distance_m / REFERENCE_DISTANCE_M
    return corner(angle_deg, distance_m, 0.8, 96 // shrink, 128 // shrink, board_m=BOARD_M * scale,
                  half_height_m=HALF_HEIGHT_M * scale)


def corner_scans(config: Config, seed: int, shrink: int, distances: tuple[float, ...]
                 ) -> list[tuple[str, Callable[[], Scan]]]:
    """(label, render) of every scan measured: the scene set's corners, the external corners, the scaled corners."""
    scans: list[tuple[str, Callable[[], Scan]]] = []
    for index, (label, factory, edge) in enumerate(scene_set(shrink)):
        if edge is not None:
            scans.append((label, partial(_rendered, factory, config, (seed, index))))
    for k, radius in enumerate((0.004, 0.02)):
        scans.append((f"external corner 90 deg, footprint {radius * 1e3:g} mm",
                      partial(external_corner, radius, config, np.random.default_rng([seed, 100 + k]), shrink)))
    for j, (angle, distance) in enumerate((a, d) for a in ANGLES_DEG for d in distances):
        scans.append((f"corner {angle:g} deg at {distance:g} m (scaled)",
                      partial(_rendered, partial(scaled_corner, angle, distance, shrink), config, (seed, 200 + j))))
    return scans


def _rendered(factory: Callable[[], Scene], config: Config, key: tuple[int, int]) -> Scan:
    return render(factory(), config, np.random.default_rng(list(key)))


def reach_of(prior: PriorConfig) -> tuple[float, float]:
    """The largest rho_ABA [1] and d_AB [m] of a prior."""
    reach = PriorCard(**prior.model_dump(mode="json")).multipath_reach()
    assert reach is not None
    return reach


def quantile_cells(values: NDArray[np.float64]) -> str:
    if not values.size:
        return " | ".join("" for _ in QUANTILES)
    return " | ".join(f"{q:.3g}" for q in np.quantile(values, QUANTILES))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--shrink", type=int, default=1, help="Divide every scene's height and width by this.")
    parser.add_argument("--distances", type=float, nargs="*", default=list(DISTANCES_M))
    parser.add_argument("--rho-aba-max", type=float, help="Also the share inside a prior of this largest rho_ABA.")
    parser.add_argument("--d-ab-max", type=float, help="... and this largest d_AB [m].")
    args = parser.parse_args()
    started = time.perf_counter()
    config = Config()
    priors = {"wide": reach_of(preset("wide").prior), "default": reach_of(config.prior)}
    if args.rho_aba_max is not None or args.d_ab_max is not None:
        priors["given"] = (args.rho_aba_max or priors["wide"][0], args.d_ab_max or priors["wide"][1])
    print("Priors (largest rho_ABA, d_AB [m]): " + ", ".join(f"{k} ({r:.3g}, {d:.3g})" for k, (r, d) in
                                                            priors.items()) + "\n")
    names = ("rho_ABA", "d_AB [m]", "coupling")
    print("| scene | corrected pixels | " + " | ".join(f"{n} {100 * q:g} %" for n in names for q in QUANTILES)
          + " | " + " | ".join(f"inside {k} [%]" for k in priors) + " |")
    print("|---" * (2 + len(names) * len(QUANTILES) + len(priors)) + "|")
    collected = []
    for label, make in corner_scans(config, args.seed, args.shrink, tuple(args.distances)):
        found = gated_inputs(make(), config)
        collected.append(found.values)
        print(row(label, found, priors), flush=True)
    print(row("**all**", GatedInputs(np.concatenate(collected)), priors))
    print(f"\n{platform.system()}, {platform.machine()}, Python {platform.python_version()}, {date.today()}, "
          f"{time.perf_counter() - started:.0f} s wall")


def row(label: str, found: GatedInputs, priors: dict[str, tuple[float, float]]) -> str:
    cells = [quantile_cells(found.values[:, k]) for k in range(3)]
    inside = " | ".join(f"{100 * found.inside(reach):.1f}" for reach in priors.values())
    return f"| {label} | {found.values.shape[0]:,} | {' | '.join(cells)} | {inside} |"


if __name__ == "__main__":
    main()
