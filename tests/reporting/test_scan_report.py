"""Per-scan outputs: the rasterized point-cloud views, the output levels and the thumbnail."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import json
from dataclasses import replace
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, Flag
from mpi_lidar.reporting.scan_report import (
    DEFAULT_OUTPUTS,
    FLAG_COLOURS,
    OUTPUT_LEVELS,
    THUMBNAIL_PX,
    _mean_raster,
    covers,
    point_cloud_figure,
    thumbnail_image,
)
from mpi_lidar.scans.scan import write_scan
from mpi_lidar.simulation.scenes import cornered_board, render
from mpi_lidar.workflows.correct_archive import process_scan
from tests.model_factory import tiny_model


def test_mean_raster__mean_per_cell_and_nan_where_empty():
    u = np.array([0.1, 0.1, 0.9, 0.5])
    v = np.array([0.1, 0.1, 0.9, 0.1])
    value = np.array([1.0, 3.0, 5.0, 7.0])
    image = _mean_raster(u, v, value, (0.0, 1.0, 0.0, 1.0), bins=2)
    assert image[0, 0] == 2.0  # rows along v, columns along u: both points of the lower-left cell
    assert image[0, 1] == 7.0
    assert image[1, 1] == 5.0
    assert np.isnan(image[1, 0])


def test_point_cloud_figure__images_not_markers_for_a_million_points():
    points = np.random.default_rng(0).normal(size=(1000, 1000, 3)) + np.array([0.0, 0.0, 2.0])
    points[0, :10] = np.nan  # invalid pixels are left out, not drawn at the origin
    fig = point_cloud_figure(points, points + 0.01)
    views = [ax for ax in fig.axes if ax.get_title()]
    assert len(views) == 4
    assert all(len(ax.collections) == 0 and len(ax.images) == 1 for ax in views)
    assert "999,990 points" in fig.axes[0].get_title()


# --- output levels ----------------------------------------------------------------------------------------

FILES = {
    "data": {"corrected.zarr", "metrics.json"},
    "light": {"corrected.zarr", "metrics.json", "report.md", "report.html", "thumbnail.png"},
    "full": {"corrected.zarr", "metrics.json", "report.md", "report.html", "maps.png", "error_hist.png",
             "point_cloud.png", "raw.ply", "corrected.ply", "corrected.las", "plotly.min.js"},
}
GEOMETRY_FILES = {"point_cloud.png", "raw.ply", "corrected.ply", "corrected.las", "plotly.min.js"}


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    return tiny_model(tmp_path_factory.mktemp("model") / "model")


@pytest.fixture(scope="module")
def board_store(tmp_path_factory) -> Path:
    scan = render(cornered_board(height=40, width=56), Config(), np.random.default_rng(3))
    return write_scan(scan, tmp_path_factory.mktemp("scans") / "board.scan.zarr")


def _listing(path: Path) -> set[str]:
    return {p.name for p in path.iterdir() if not p.name.startswith(".")}


@pytest.mark.parametrize("level", OUTPUT_LEVELS)
def test_write_scan_outputs__each_level_writes_its_files_and_says_which(level, model_dir, board_store, tmp_path):
    outcome = process_scan(board_store, model_dir, tmp_path, CorrectionOptions(), outputs=level)
    assert outcome.status == "corrected", outcome.reason
    target = Path(outcome.output)
    assert _listing(target) == FILES[level]
    data = json.loads((target / "metrics.json").read_text())
    assert data["outputs"] == {"level": level, "files": sorted(FILES[level])}
    assert data["counts"]["corrected"] == outcome.counts["corrected"] > 0 and data["metrics"] == outcome.metrics
    if level != "data":
        report = (target / "report.md").read_text()
        assert f"Outputs (level {level}): " + ", ".join(sorted(FILES[level])) in report
        assert all(f"]({name})" in report for name in FILES[level] if name.endswith(".png"))


def test_thumbnail__at_most_512_pixels_depth_left_flags_right(model_dir, board_store, tmp_path):
    outcome = process_scan(board_store, model_dir, tmp_path, CorrectionOptions(), outputs="light")
    image = matplotlib.image.imread(Path(outcome.output) / "thumbnail.png")
    assert image.shape[1] == 2 * 56 + 4 and image.shape[0] == 40  # small scans are shown at full size
    report = (Path(outcome.output) / "report.md").read_text()
    assert "Thumbnail: corrected depth (left" in report and FLAG_COLOURS[0] in report
    from mpi_lidar.correction import Correction

    flags = np.full((1500, 3000), Flag.NO_MULTIPATH, dtype=np.uint8)
    flags[:, :1500] = Flag.CORRECTED
    depth = np.tile(np.linspace(1.0, 3.0, 3000, dtype=np.float32), (1500, 1))
    depth[0, 0] = np.nan
    big, (low, high) = thumbnail_image(Correction(depth, flags, 0.0, 0.0))
    assert max(big.shape[:2]) <= THUMBNAIL_PX and big.dtype == np.uint8 and big.shape[2] == 3
    assert 1.0 <= low < high <= 3.0
    half = big.shape[1] // 2 + 2
    assert tuple(big[10, half + 2]) == tuple(int(FLAG_COLOURS[Flag.CORRECTED][i:i + 2], 16) for i in (1, 3, 5))
    assert tuple(big[10, -2]) == tuple(int(FLAG_COLOURS[Flag.NO_MULTIPATH][i:i + 2], 16) for i in (1, 3, 5))
    assert tuple(big[0, 0]) == (255, 255, 255), "invalid pixels are white"


def test_output_level__is_no_part_of_the_hash_a_higher_level_is_kept_a_lower_one_completed(
        model_dir, board_store, tmp_path):
    options = CorrectionOptions()
    assert DEFAULT_OUTPUTS == "light"
    first = process_scan(board_store, model_dir, tmp_path, options, outputs="light")
    assert first.status == "corrected"
    again = process_scan(board_store, model_dir, tmp_path, options, outputs="data")
    assert again.status == "skipped" and again.counts == first.counts, "light holds everything data writes"
    more = process_scan(board_store, model_dir, tmp_path, options, outputs="full")
    assert more.status == "corrected" and _listing(Path(more.output)) == FILES["full"]
    assert process_scan(board_store, model_dir, tmp_path, options, outputs="light").status == "skipped"
    assert covers(None, "full") and covers("full", "data") and not covers("data", "light")


def test_output_level__scan_without_geometry_at_full_says_point_clouds_were_skipped(model_dir, tmp_path):
    scan = render(cornered_board(height=24, width=32), Config(), np.random.default_rng(1))
    store = write_scan(replace(scan, azimuth_rad=None, elevation_rad=None), tmp_path / "flat.scan.zarr")
    pixelwise = tiny_model(tmp_path / "model", geometric=False)
    outcome = process_scan(store, pixelwise, tmp_path / "out", CorrectionOptions(), outputs="full")
    assert "no scan geometry: point clouds and views skipped" in outcome.notes
    assert _listing(Path(outcome.output)) == FILES["full"] - GEOMETRY_FILES
    light = process_scan(store, pixelwise, tmp_path / "light", CorrectionOptions(), outputs="light")
    assert not any("point clouds" in note for note in light.notes), "light never writes point clouds"


def test_output_level__unknown_level_is_one_clear_error(model_dir, board_store, tmp_path):
    from mpi_lidar.errors import MpiLidarError
    from mpi_lidar.workflows.correct_archive import correct_archive

    with pytest.raises(MpiLidarError, match="unknown output level 'everything'; choose one of full, light, data"):
        correct_archive([str(board_store)], model_dir, tmp_path, CorrectionOptions(), outputs="everything")
    assert not any(tmp_path.iterdir()), "refused before anything is written"
