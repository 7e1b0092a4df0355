"""Sensor simulator figures: speed per core of both fidelities, raw and noise-only MAE, depth noise std.

Run: .venv/bin/python -m benchmarks.sensor [--rows N] [--waveform-rows N] [--draws N]
Prints markdown tables; docs/results/sensor.md records them with machine and date.
"""

from __future__ import annotations

import argparse
import platform
import time
from datetime import date

import numpy as np

from mpi_lidar.config import Config
from mpi_lidar.physics import MomentSensor, make_sensor
from mpi_lidar.physics.demod import unambiguous_range
from mpi_lidar.simulation.sampling import sample_theta


def samples_per_second(fidelity: str, rows: int, repeats: int = 3) -> float:
    """Best of ``repeats`` single-process runs over theta from the default prior, all four frequencies."""
    config = Config().replace(simulator={"fidelity": fidelity})
    sensor = make_sensor(config)
    theta = sample_theta(config.prior, rows, np.random.default_rng(0))
    best = np.inf
    for seed in range(repeats):
        started = time.perf_counter()
        sensor.measure(theta, np.random.default_rng(seed))
        best = min(best, time.perf_counter() - started)
    return rows / best


def raw_errors(rows: int) -> tuple[np.ndarray, np.ndarray]:
    """MAE per frequency with multipath, and without it (noise only), on the same scenes. [m]"""
    config = Config()
    sensor = make_sensor(config)
    theta = sample_theta(config.prior, rows, np.random.default_rng(1))
    depth, _ = sensor.measure(theta, np.random.default_rng(2))
    clean, _ = sensor.measure(theta, np.random.default_rng(3), multipath=False)
    return np.abs(depth - theta[:, :1]).mean(0), np.abs(clean - theta[:, :1]).mean(0)


def depth_noise_std(d_as: float, rho: float, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Analytic (moment model) and simulated depth std per frequency without multipath. [m]"""
    config = Config()
    sensor = MomentSensor(config)
    theta = np.tile([d_as, 0.0, rho, 0.0, 0.0, 0.0], (rows, 1))
    mean, cov = sensor.quadrature_moments(theta[:1])
    phase = np.arctan2(mean[0, :, 1], mean[0, :, 0])
    tangent = np.stack([-np.sin(phase), np.cos(phase)], -1)
    perpendicular_var = np.einsum("fi,fij,fj->f", tangent, cov[0], tangent)
    amplitude = np.hypot(mean[0, :, 0], mean[0, :, 1])
    metres_per_rad = unambiguous_range(config.frequencies_hz, config.sensor.speed_of_light_m_per_s) / (2 * np.pi)
    analytic = np.sqrt(perpendicular_var) / amplitude * metres_per_rad
    depth, _ = sensor.measure(theta, np.random.default_rng(4))
    return analytic, depth.std(0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=400_000, help="rows for the moment speed and MAE runs")
    parser.add_argument("--waveform-rows", type=int, default=3_000, help="rows for the waveform speed run")
    parser.add_argument("--draws", type=int, default=100_000, help="draws per simulated depth noise std")
    args = parser.parse_args()
    freqs = [f"{f / 1e6:g} MHz" for f in Config().frequencies_hz]
    print(f"Machine: {platform.node()} ({platform.machine()}, {platform.python_version()}), {date.today()}\n")

    print("| fidelity | samples/s per core (4 frequencies) |\n|---|---|")
    print(f"| moment | {samples_per_second('moment', args.rows):,.0f} |")
    print(f"| waveform | {samples_per_second('waveform', args.waveform_rows, repeats=2):,.0f} |\n")

    mae, noise = raw_errors(args.rows)
    print("| | " + " | ".join(freqs) + " |\n|---|" + "---|" * len(freqs))
    print("| raw MAE [mm] | " + " | ".join(f"{1e3 * v:.3f}" for v in mae) + " |")
    print("| noise-only MAE [mm] | " + " | ".join(f"{1e3 * v:.3f}" for v in noise) + " |\n")

    print(f"Depth noise std without multipath, analytic / simulated ({args.draws:,} draws) [mm]\n")
    print("| d_AS | rho_SAS | " + " | ".join(freqs) + " |\n|---|---|" + "---|" * len(freqs))
    for d_as in (1.4, 2.4):
        for rho in (0.1, 0.5, 1.0):
            analytic, simulated = depth_noise_std(d_as, rho, args.draws)
            cells = " | ".join(f"{1e3 * a:.3f} / {1e3 * s:.3f}" for a, s in zip(analytic, simulated, strict=True))
            print(f"| {d_as} m | {rho} | {cells} |")


if __name__ == "__main__":
    main()
