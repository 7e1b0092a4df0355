"""Bayes limit against raw depth and the physics solvers, per noise scale.

    .venv/bin/python -m benchmarks.limits [--n-test 1000] [--pool 1000] [--seed 7] [--scales 1,0.3,0.1,0.01]
                                          [--no-round] [--solvers-only]

For each noise scale: a test set of ``n-test`` rows drawn from the default (reciprocal) prior and measured by
the moment-matched sensor; the posterior-median MAE and posterior-mean RMSE with pool M and, on the same
rows, with pool 2M (the convergence check: the two MAEs and the mean absolute change of the per-row
median); the median effective sample size; the MAE of the raw 31.25 MHz depth, of the Prony fit and of the
bounded least-squares fit. Standard errors are over test rows. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mpi_lidar.config import Config
from mpi_lidar.learning.limits import bayes_limit, posterior_estimates
from mpi_lidar.physics.inverse import FIT_OK, least_squares_two_path, prony_two_path, unwrapped_weighted_depth
from mpi_lidar.physics.moments import MomentSensor
from mpi_lidar.simulation.sampling import sample_theta


def run(scale: float, n_test: int, pool: int, seed: int, round_photons: bool) -> dict[str, float]:
    config = Config().replace(simulator={"noise_scale": scale, "round_photons": round_photons})
    rng = np.random.default_rng([seed, round(scale * 1e6)])
    start = time.perf_counter()
    result = bayes_limit(config, n_test, rng, pool=pool)
    seconds = time.perf_counter() - start
    double = posterior_estimates(result.raw, config, rng, pool=2 * pool)
    truth = result.theta[:, 0]
    freqs = np.asarray(config.frequencies_hz)
    prony = prony_two_path(result.raw, freqs)
    nls = least_squares_two_path(result.raw, freqs, start=prony)
    abs2 = np.abs(double.median_m - truth)
    return {
        "scale": scale,
        "mae": result.mae_m * 1e3,
        "mae_se": result.mae_se_m * 1e3,
        "rmse": result.rmse_m * 1e3,
        "rmse_se": result.rmse_se_m * 1e3,
        "ess": result.median_ess,
        "ess_p10": float(np.percentile(result.ess, 10)),
        "mae_2m": float(abs2.mean()) * 1e3,
        "rmse_2m": float(np.sqrt(((double.mean_m - truth) ** 2).mean())) * 1e3,
        "ess_2m": float(np.median(double.ess)),
        "median_shift": float(np.abs(double.median_m - result.posterior_median_m).mean()) * 1e3,
        "raw": result.raw_mae_m * 1e3,
        "prony": float(np.abs(prony.direct_depth_m - truth).mean()) * 1e3,
        "prony_ok": float((prony.status == FIT_OK).mean()),
        "nls": float(np.abs(nls.direct_depth_m - truth).mean()) * 1e3,
        "nls_ok": float((nls.status == FIT_OK).mean()),
        "seconds": seconds,
    }


def run_solvers(scale: float, n_test: int, seed: int, round_photons: bool) -> dict[str, float]:
    """Raw, Prony and least-squares MAE on the very rows :func:`run` draws (same seed), without the posterior."""
    config = Config().replace(simulator={"noise_scale": scale, "round_photons": round_photons})
    rng = np.random.default_rng([seed, round(scale * 1e6)])
    theta = sample_theta(config.prior, n_test, rng)
    depth, amplitude = MomentSensor(config).measure(theta, rng)
    raw = np.hstack([depth, amplitude])
    truth = theta[:, 0]
    freqs = np.asarray(config.frequencies_hz)
    start = time.perf_counter()
    prony = prony_two_path(raw, freqs)
    prony_s = time.perf_counter() - start
    nls = least_squares_two_path(raw, freqs, start=prony)
    nls_s = time.perf_counter() - start - prony_s
    return {
        "scale": scale,
        "raw": float(np.abs(depth[:, -1] - truth).mean()) * 1e3,
        "weighted": float(np.abs(unwrapped_weighted_depth(raw, freqs) - truth).mean()) * 1e3,
        "prony": float(np.abs(prony.direct_depth_m - truth).mean()) * 1e3,
        "prony_ok": float((prony.status == FIT_OK).mean()),
        "prony_rows_per_s": n_test / prony_s,
        "nls": float(np.abs(nls.direct_depth_m - truth).mean()) * 1e3,
        "nls_ok": float((nls.status == FIT_OK).mean()),
        "nls_rows_per_s": n_test / nls_s,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-test", type=int, default=1000)
    parser.add_argument("--pool", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--scales", default="1,0.3,0.1,0.01")
    parser.add_argument("--no-round", action="store_true", help="simulate and infer without eq 16 rounding")
    parser.add_argument("--solvers-only", action="store_true", help="raw, weighted, Prony and NLS on the same rows")
    args = parser.parse_args()
    if args.solvers_only:
        print("| noise scale | raw 31.25 MHz MAE [mm] | weighted depth MAE [mm] | Prony MAE [mm] (fit ok) "
              "| NLS MAE [mm] (fit ok) | Prony [rows/s] | NLS [rows/s] |")
        print("|---|---|---|---|---|---|---|")
        for scale in (float(s) for s in args.scales.split(",")):
            r = run_solvers(scale, args.n_test, args.seed, not args.no_round)
            print(f"| {r['scale']:g} | {r['raw']:.3f} | {r['weighted']:.3f} | {r['prony']:.3f} ({r['prony_ok']:.0%}) "
                  f"| {r['nls']:.3f} ({r['nls_ok']:.0%}) | {r['prony_rows_per_s']:.0f} | {r['nls_rows_per_s']:.0f} |",
                  flush=True)
        return
    print(f"n_test={args.n_test} pool M={args.pool} seed={args.seed} round_photons={not args.no_round}")
    print("| noise scale | Bayes MAE (M) [mm] | Bayes MAE (2M) [mm] | mean abs median shift M->2M [mm] "
          "| Bayes RMSE (M / 2M) [mm] | median ESS (M / 2M) | ESS p10 (M) | raw 31.25 MHz MAE [mm] "
          "| Prony MAE [mm] (fit ok) | NLS MAE [mm] (fit ok) | time (M) [s] |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for scale in (float(s) for s in args.scales.split(",")):
        r = run(scale, args.n_test, args.pool, args.seed, not args.no_round)
        print(f"| {r['scale']:g} | {r['mae']:.3f} ± {r['mae_se']:.3f} | {r['mae_2m']:.3f} | {r['median_shift']:.3f} "
              f"| {r['rmse']:.3f} / {r['rmse_2m']:.3f} | {r['ess']:.0f} / {r['ess_2m']:.0f} | {r['ess_p10']:.0f} "
              f"| {r['raw']:.3f} | {r['prony']:.3f} ({r['prony_ok']:.0%}) | {r['nls']:.3f} ({r['nls_ok']:.0%}) "
              f"| {r['seconds']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
