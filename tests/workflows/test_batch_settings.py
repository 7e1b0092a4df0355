"""A batch's point-cloud settings on the command line (--point-cloud-frame, --no-return-range), and a re-run into
an --out made with other settings: refused whole, or with --replace-options corrected and summarised with the
scans earlier batches left there."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import laspy
import numpy as np
import pytest

from mpi_lidar.scans.store import write_scan
from tests.cli_runner import assert_one_error_line, call_main
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    return tiny_model(tmp_path_factory.mktemp("model") / "model")


def _files(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()}


def test_correct_cli__z_up_frame_and_no_return_pixels_on_their_ray(model, tmp_path, monkeypatch, capsys):
    scan = two_path_scan("a", height=8, width=10)
    amplitude = np.array(scan.amplitude)
    amplitude[:, 0, :3] = 0.0  # three pixels without a return
    write_scan(replace(scan, amplitude=amplitude), tmp_path / "scans" / "a.scan.zarr")
    runs = {}
    for frame, extra in (("scanner", []), ("z-up", ["--no-return-range", "30"])):
        out = tmp_path / frame
        code, _, err = call_main(monkeypatch, capsys, "correct", tmp_path / "scans", "--model", model, "--out", out,
                                 "--gate", "all", "--outputs", "data", "--point-cloud", "las",
                                 "--point-cloud-frame", frame, *extra)
        assert code == 0, err
        runs[frame] = laspy.read(out / "a" / "corrected.las")
        attrs = json.loads((out / "a" / "corrected.zarr" / "zarr.json").read_text())["attributes"]
        assert attrs["point_cloud_placement"].startswith(f"frame {frame};")
    scanner, z_up = runs["scanner"], runs["z-up"]
    assert len(z_up.x) == len(scanner.x) + 3
    x, y, z = (np.asarray(z_up[axis], dtype=np.float64) for axis in "xyz")
    withheld = np.asarray(z_up.withheld, dtype=bool)
    assert float(np.median(scanner.z)) > 1.5 and float(np.median(x[~withheld])) > 1.5  # forward: z, then x
    far = np.sqrt(x**2 + y**2 + z**2) > 29
    assert far.sum() == 3 and withheld[far].all() and (x[far] > 0).all()


def test_correct_cli__other_options_into_the_same_out_refused_unless_replaced(model, tmp_path, monkeypatch, capsys):
    for seed, name in enumerate(("a", "b", "c")):
        write_scan(two_path_scan(name, height=8, width=10, seed=seed), tmp_path / "scans" / f"{name}.scan.zarr")
    args = ["--model", model, "--out", tmp_path / "out", "--gate", "all", "--outputs", "data"]
    code, _, err = call_main(monkeypatch, capsys, "correct", tmp_path / "scans", *args)
    assert code == 0, err
    before = _files(tmp_path / "out")
    code, out, err = call_main(monkeypatch, capsys, "correct", tmp_path / "scans" / "a.scan.zarr", *args,
                               "--baseline", "raw")
    assert code == 2 and out == ""
    assert_one_error_line(err, "corrected with other settings")
    assert "--replace-options" in err
    assert _files(tmp_path / "out") == before, "a refused batch writes nothing"
    code, out, err = call_main(monkeypatch, capsys, "correct", tmp_path / "scans" / "a.scan.zarr", *args,
                               "--baseline", "raw", "--replace-options")
    assert code == 0, err
    summary = (tmp_path / "out" / "summary" / "report.md").read_text()
    assert summary.startswith("# Batch correction\n\n3 scans in") and "kept from an earlier batch" in summary
    assert all(f"\n| {name} | " in summary for name in ("a", "b", "c"))
    assert "(baseline=raw, gate=all)" in summary and "(1 scan)" in summary and "(2 scans)" in summary
