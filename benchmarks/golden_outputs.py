"""Golden outputs: the correction's outputs on a fixed set of scenes, kept to prove a refactor changes nothing.

Run: .venv/bin/python -m benchmarks.golden_outputs make --out DIR       (scans, a model and their outputs)
 or: .venv/bin/python -m benchmarks.golden_outputs compare --golden DIR  (the same scans and model, corrected
     again by this checkout, against what ``make`` wrote)

``make`` renders every scene of the scene set (and a wall and a corner at 6 m, whose depths wrap, and a corner
in a scanner's counts), trains a small model in this process, and writes each case's outputs at the default
output level (``corrected.zarr`` and ``corrected.laz``) under ``DIR/outputs/<case>``. ``compare`` corrects the
same stored scans with the same stored model into a temporary folder and prints, per case, the largest
difference of every depth-like array of ``corrected.zarr`` [m] and of every LAZ record, and the share of pixels
whose flag or estimate differs. It exits 1 where a difference exceeds 1e-6 m or more than 0.01 % of the flags
differ, except for the cases listed in ``EXPECTED_CHANGES`` (reported, never a failure).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.simulation.scenes import SCENES, corner, flat_wall, render

ATOL_M = 1e-6
MAX_FLAG_SHARE = 1e-4
# Integer-coded maps compared by their share of differing pixels; every other array by its largest difference.
CODED = ("flags", "estimate")
# A profile's noise scale reaches every stage now: its case may move, and says by how much.
EXPECTED_CHANGES = ("cornered_board_noise_x2",)


def _cases() -> dict[str, tuple[str, dict]]:
    """Case name -> (scan name, correction options)."""
    cases: dict[str, tuple[str, dict]] = {name: (name, {}) for name in SCENES}
    cases.update({"wall_6m": ("wall_6m", {}), "corner_6m": ("corner_6m", {}),
                  "corner_counts_auto": ("corner_counts", {}),
                  "corner_counts_given": ("corner_counts", {"amplitude_scale": 4000.0}),
                  "cornered_board_raw_baseline": ("cornered_board", {"baseline": "raw"}),
                  "cornered_board_gate_all": ("cornered_board", {"gate": "all"}),
                  "cornered_board_noise_x2": ("cornered_board", {"noise_scale": 2.0})})
    return cases


def make(out: Path) -> None:
    from dataclasses import replace

    from mpi_lidar.scans.store import write_scan
    from tests.model_factory import tiny_model

    config = Config()
    scans = out / "scans"
    for index, name in enumerate(SCENES):
        write_scan(render(SCENES[name](), config, np.random.default_rng(index)), scans / f"{name}.scan.zarr")
    far = {"wall_6m": flat_wall(15.0, 6.0, 0.7, height=48, width=64),
           "corner_6m": corner(90.0, 6.0, 0.8, height=48, width=64)}
    for index, (name, scene) in enumerate(far.items()):
        scan = render(scene, config, np.random.default_rng(100 + index), patch_spacing_m=0.1)
        write_scan(replace(scan, name=name), scans / f"{name}.scan.zarr")
    counts = render(corner(90.0, 2.0, 0.8, height=48, width=64), config, np.random.default_rng(200))
    write_scan(replace(counts, name="corner_counts", amplitude=(counts.amplitude * 4000.0).astype(np.float32)),
               scans / "corner_counts.scan.zarr")
    tiny_model(out / "model", rows=20_000, rounds=60, config=config)
    _correct_all(out, out / "outputs")
    print(f"golden outputs in {out}")


def _correct_all(golden: Path, outputs: Path) -> None:
    from mpi_lidar.workflows.correct_archive import process_scan

    for case, (scan_name, options) in _cases().items():
        outcome = process_scan(golden / "scans" / f"{scan_name}.scan.zarr", golden / "model", outputs,
                               CorrectionOptions(**options), output=case, outputs="light")
        print(f"{case}: {outcome.status.value} {outcome.reason}".rstrip())


def compare(golden: Path) -> int:
    with tempfile.TemporaryDirectory() as tmp:
        _correct_all(golden, Path(tmp))
        failures = [case for case in _cases() if not _compare_case(golden / "outputs" / case, Path(tmp) / case)
                    and case not in EXPECTED_CHANGES]
    print("golden outputs: " + ("all equal" if not failures else f"differ in {', '.join(failures)}"))
    return 1 if failures else 0


def _compare_case(before: Path, after: Path) -> bool:
    import laspy
    import xarray as xr

    same = True
    lines = []
    with xr.open_zarr(before / "corrected.zarr") as old, xr.open_zarr(after / "corrected.zarr") as new:
        for name in sorted(set(old.data_vars) | set(new.data_vars)):
            if name not in old.data_vars or name not in new.data_vars:
                lines.append(f"  {name}: only in {'after' if name in new.data_vars else 'before'}")
                same = False
                continue
            a, b = np.asarray(old[name]), np.asarray(new[name])
            if name in CODED:
                share = float(np.mean(a != b))
                same &= share <= MAX_FLAG_SHARE
                if share:
                    lines.append(f"  {name}: {share:.4%} of pixels differ ({int(np.sum(a != b))})")
            else:
                diff = _largest_difference(a, b)
                same &= diff <= ATOL_M
                if diff:
                    lines.append(f"  {name}: largest difference {diff:.3g}")
    if (before / "corrected.laz").exists() or (after / "corrected.laz").exists():
        old_cloud, new_cloud = laspy.read(before / "corrected.laz"), laspy.read(after / "corrected.laz")
        if len(old_cloud.points) != len(new_cloud.points):
            lines.append(f"  LAZ: {len(old_cloud.points)} points before, {len(new_cloud.points)} after")
            same = False
        else:
            for dimension in _laz_dimensions(old_cloud):
                a = np.asarray(old_cloud[dimension], dtype=np.float64)
                b = np.asarray(new_cloud[dimension], dtype=np.float64)
                if np.issubdtype(np.asarray(old_cloud[dimension]).dtype, np.integer):  # a code or a count
                    # The intensity is a rounded amplitude: a last-bit move of the amplitude may round it one
                    # count the other way.
                    share = float(np.mean(np.abs(a - b) > (1 if dimension == "intensity" else 0)))
                    same &= share <= MAX_FLAG_SHARE
                    if share:
                        lines.append(f"  LAZ {dimension}: {share:.4%} of points differ ({int(np.sum(a != b))})")
                    continue
                diff = _largest_difference(a, b) * (1e-3 if dimension.endswith("_mm") else 1.0)  # in metres
                if diff:
                    lines.append(f"  LAZ {dimension}: largest difference {diff:.3g} m")
                same &= diff <= ATOL_M
    print(f"{before.name}: {'equal' if same else 'DIFFERENT'}")
    for line in lines:
        print(line)
    return same


def _laz_dimensions(cloud) -> list[str]:
    """The LAZ record's dimensions as a reader sees them: x, y, z in metres instead of their scaled integers."""
    names = [name for name in cloud.point_format.dimension_names if name not in ("X", "Y", "Z")]
    return ["x", "y", "z", *names]


def _largest_difference(a: np.ndarray, b: np.ndarray) -> float:
    if a.shape != b.shape:
        return float("inf")
    a, b = a.astype(np.float64), b.astype(np.float64)
    nan_mismatch = np.isnan(a) != np.isnan(b)
    if nan_mismatch.any():
        return float("inf")
    both = ~np.isnan(a)
    return float(np.max(np.abs(a[both] - b[both]), initial=0.0))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("make").add_argument("--out", type=Path, required=True)
    sub.add_parser("compare").add_argument("--golden", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.command == "make":
        make(args.out)
        return 0
    return compare(args.golden)


if __name__ == "__main__":
    sys.exit(main())
