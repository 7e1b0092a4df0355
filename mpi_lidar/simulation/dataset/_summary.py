"""A dataset's summary: the raw depth error of each frequency, with and without multipath."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np

from mpi_lidar.physics.noise import unwrapped_rows
from mpi_lidar.simulation.dataset._chunks import SPLIT_CODES, cached_sensor, prior_wraps, seeded_rng
from mpi_lidar.simulation.dataset._readers import read_verified
from mpi_lidar.simulation.dataset._store import open_store, store_config

# Stream of the seed tree reserved for summary statistics, apart from the chunk streams (seed, i).
SUMMARY_STREAM = (1, 0)


@dataclass(frozen=True)
class DatasetSummary:
    """Raw depth errors of a dataset, per frequency. Errors in metres."""

    path: str
    samples: int
    train: int
    test: int
    frequencies_hz: tuple[float, ...]
    mae_m: tuple[float, ...]
    rmse_m: tuple[float, ...]
    noise_only_mae_m: tuple[float, ...]
    noise_only_rows: int
    config_sha256: str

    def to_markdown(self) -> str:
        lines = [
            f"Dataset `{self.path}`: {self.samples:,} rows ({self.train:,} train, {self.test:,} test), "
            f"config {self.config_sha256[:12]}",
            "",
            "| frequency | raw MAE [mm] | raw RMSE [mm] | noise-only MAE [mm] |",
            "|---|---|---|---|",
        ]
        for f, mae, rmse, noise in zip(self.frequencies_hz, self.mae_m, self.rmse_m, self.noise_only_mae_m,
                                       strict=True):
            lines.append(f"| {f / 1e6:g} MHz | {mae * 1e3:.3f} | {rmse * 1e3:.3f} | {noise * 1e3:.3f} |")
        lines += ["", f"Noise-only: the same scenes without the A -> B -> A path, first {self.noise_only_rows:,} rows."]
        return "\n".join(lines)


def summarize(path: str | Path, noise_only_rows: int = 200_000) -> DatasetSummary:
    """Raw MAE and RMSE of each frequency's depth against the truth, and the noise-only MAE.

    The noise-only MAE simulates the first ``noise_only_rows`` scenes again without multipath, from a
    stream of the seed tree reserved for it, so it is reproducible and independent of the stored noise.
    """
    group = open_store(path)
    config = store_config(group)
    n_freq = len(config.frequencies_hz)
    stored = read_verified(path)
    error = stored["features"][:, :n_freq].astype(np.float64) - stored["target"][:, None]
    split = stored["split"]
    rows = min(noise_only_rows, config.dataset.samples)
    theta = stored["theta"][:rows]
    clean_depth, clean_amplitude = cached_sensor(config).measure(
        theta, seeded_rng(config.dataset.seed, *SUMMARY_STREAM), multipath=False)
    if prior_wraps(config):  # as the stored rows are
        clean = np.concatenate([clean_depth, clean_amplitude], axis=1).astype(np.float32)
        clean_depth = unwrapped_rows(clean, config.frequencies_hz, config.sensor)[0][:, :n_freq].astype(np.float64)
    noise_error = clean_depth - theta[:, :1]
    return DatasetSummary(
        path=str(path),
        samples=config.dataset.samples,
        train=int((split == SPLIT_CODES["train"]).sum()),
        test=int((split == SPLIT_CODES["test"]).sum()),
        frequencies_hz=config.frequencies_hz,
        mae_m=tuple(np.abs(error).mean(0).tolist()),
        rmse_m=tuple(np.sqrt((error**2).mean(0)).tolist()),
        noise_only_mae_m=tuple(np.abs(noise_error).mean(0).tolist()),
        noise_only_rows=rows,
        config_sha256=cast(str, group.attrs["config_sha256"]),
    )
