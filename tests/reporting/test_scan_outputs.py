"""Per-scan outputs of an archived scan (no reference depth): what correction did in maps.png, the point clouds
through the LAS/PLY writers, and the interactive 3-D view of report.html."""

from __future__ import annotations

import matplotlib

from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2

matplotlib.use("Agg")

import json
from dataclasses import replace
from pathlib import Path

import laspy
import numpy as np
import pytest
from plyfile import PlyData

from mpi_lidar.correction import CorrectionOptions, Flag
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.reporting.scan_report import (
    PLOTLY_JS,
    VIEW_3D_FALLBACK,
    VIEW_3D_POINTS,
    applied_correction_mm,
    maps_figure,
    point_cloud_formats,
    point_cloud_view_3d,
)
from mpi_lidar.scans.scan import write_scan
from mpi_lidar.workflows.correct_archive import correct_archive, process_scan
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

FIELDS = {"raw_range_m", "corrected_range_m", "correction_mm", "flag", "amplitude_v2", "row", "column"}


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    return tiny_model(tmp_path_factory.mktemp("model") / "model")


@pytest.fixture(scope="module")
def archived(tmp_path_factory):
    """A scan as an archive holds it: geometry, no reference depth."""
    scan = replace(two_path_scan("archived"), reference_depth=None, reference_mask=None)
    return scan, write_scan(scan, tmp_path_factory.mktemp("scans") / "archived.scan.zarr")


@pytest.fixture(scope="module")
def full_outputs(model_dir, archived, tmp_path_factory) -> Path:
    outcome = process_scan(archived[1], model_dir, tmp_path_factory.mktemp("out"), CorrectionOptions(gate="all"),
                           outputs="full")
    assert outcome.status == "corrected", outcome.reason
    return Path(outcome.output)


def test_full__archived_scan_writes_maps_named_point_clouds_and_the_3d_view(full_outputs, archived):
    scan = archived[0]
    names = {p.name for p in full_outputs.iterdir()}
    assert {"maps.png", "point_cloud.png", "raw.ply", "corrected.ply", "corrected.las", PLOTLY_JS} <= names
    assert "error_hist.png" not in names
    raw, corrected = (PlyData.read(str(full_outputs / name))["vertex"] for name in ("raw.ply", "corrected.ply"))
    assert {p.name for p in corrected.properties} == {"x", "y", "z"} | FIELDS
    assert raw.count == corrected.count > 0
    # the raw cloud lies at the raw range, the corrected one at the corrected range, pixel by pixel
    row, column = np.asarray(corrected["row"]), np.asarray(corrected["column"])
    for cloud, field in ((raw, "raw_range_m"), (corrected, "corrected_range_m")):
        radius = np.sqrt(np.asarray(cloud["x"], float) ** 2 + np.asarray(cloud["y"], float) ** 2
                         + np.asarray(cloud["z"], float) ** 2)
        np.testing.assert_allclose(radius, np.asarray(cloud[field], float), atol=1e-5)
    np.testing.assert_allclose(np.asarray(raw["raw_range_m"]), scan.depth[-1][row, column])
    las = laspy.read(full_outputs / "corrected.las")
    assert str(las.header.version) == "1.4" and len(las.points) == corrected.count
    assert set(las.point_format.extra_dimension_names) >= FIELDS
    np.testing.assert_allclose(np.asarray(las["raw_range_m"]), scan.depth[-1][las["row"], las["column"]])
    html = (full_outputs / "report.html").read_text()
    assert 'class="plotly-graph-div"' in html and f'<script src="{PLOTLY_JS}"></script>' in html
    assert "cdn.plot.ly" not in html and "https://" not in html.split("<body>")[0], "no CDN: archives are offline"
    assert (full_outputs / PLOTLY_JS).stat().st_size > 1_000_000
    assert VIEW_3D_FALLBACK in (full_outputs / "report.md").read_text()
    files = json.loads((full_outputs / "metrics.json").read_text())["outputs"]["files"]
    assert {"corrected.las", "raw.ply", "corrected.ply", PLOTLY_JS} <= set(files)


def test_light__no_point_clouds_unless_asked(model_dir, archived, tmp_path):
    light = process_scan(archived[1], model_dir, tmp_path / "light", CorrectionOptions(gate="all"), outputs="light")
    names = {p.name for p in Path(light.output).iterdir()}
    assert not names & {"raw.ply", "corrected.ply", "corrected.las", "corrected.laz", PLOTLY_JS}
    outcomes = correct_archive([str(archived[1])], model_dir, tmp_path / "asked", CorrectionOptions(gate="all"),
                               outputs="light", point_clouds=("laz",))
    names = {p.name for p in Path(outcomes[0].output).iterdir()}
    assert "corrected.laz" in names and not names & {"raw.ply", "corrected.ply", "corrected.las", PLOTLY_JS}
    assert set(laspy.read(Path(outcomes[0].output) / "corrected.laz").point_format.extra_dimension_names) >= FIELDS
    # the light outputs exist, but without the PLY files asked for now: corrected again to add them
    again = process_scan(archived[1], model_dir, tmp_path / "light", CorrectionOptions(gate="all"), outputs="light",
                         point_clouds=("ply",))
    assert again.status == "corrected" and (Path(again.output) / "corrected.ply").is_file()
    assert process_scan(archived[1], model_dir, tmp_path / "light", CorrectionOptions(gate="all"),
                        outputs="light", point_clouds=("ply",)).status == "skipped"


def test_point_cloud_formats__default_by_level_and_unknown_refused(model_dir, archived, tmp_path):
    assert point_cloud_formats("full") == ("ply", "las") and point_cloud_formats("light") == ()
    assert point_cloud_formats("data", ["laz", "ply", "laz"]) == ("ply", "laz")
    assert point_cloud_formats("full", ()) == ()
    with pytest.raises(MpiLidarError, match="unknown point cloud format 'xyz'"):
        correct_archive([str(archived[1])], model_dir, tmp_path / "out", CorrectionOptions(), point_clouds=["xyz"])
    assert not (tmp_path / "out").exists(), "refused before anything is written"


def test_maps_figure__archived_scan_shows_what_correction_did_in_degrees(model_dir, archived):
    from mpi_lidar import correct_scan, load_model

    scan = archived[0]
    options = CorrectionOptions(gate="geometry", min_multipath_bias_m=0.0, footprint_area_m2=DEFAULT_FOOTPRINT_AREA_M2)
    correction = correct_scan(scan, load_model(model_dir), options)
    assert correction.multipath_bias_m is not None
    fig = maps_figure(scan, correction)
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert not any("skipped" in t for t in texts), texts
    titles = [ax.get_title() for ax in fig.axes]
    assert any(t.startswith("applied correction [mm]") for t in titles)
    assert "expected multipath bias [mm]" in titles and "what was done per pixel" in titles
    maps = [ax for ax in fig.axes if ax.images]
    assert len(maps) == 6
    assert all(ax.get_xlabel() == "azimuth [deg]" and ax.get_ylabel() == "elevation [deg]" for ax in maps)
    left, right, bottom, top = maps[0].images[0].get_extent()
    assert left == pytest.approx(np.degrees(-0.2), abs=0.5) and right == pytest.approx(np.degrees(0.2), abs=0.5)
    assert {round(bottom), round(top)} == {round(np.degrees(0.15)), round(np.degrees(-0.15))}
    applied = applied_correction_mm(scan, correction)
    corrected = correction.flags == Flag.CORRECTED
    assert np.isnan(applied[~corrected]).all() and np.isfinite(applied[corrected]).any()
    np.testing.assert_allclose(applied[corrected], 1e3 * (correction.depth - scan.depth[-1])[corrected], rtol=1e-6)


def test_maps_figure__without_grid_pixel_indices_with_reference_the_error_maps(model_dir, archived):
    from mpi_lidar import correct_scan, load_model

    flat = replace(archived[0], azimuth_rad=None, elevation_rad=None)
    pixelwise = load_model(model_dir)
    fig = maps_figure(flat, correct_scan(flat, pixelwise, CorrectionOptions(gate="all")))
    maps = [ax for ax in fig.axes if ax.images]
    assert all(ax.get_xlabel() == "column [pixel]" and ax.get_ylabel() == "row [pixel]" for ax in maps)
    assert not any("skipped" in t.get_text() for ax in fig.axes for t in ax.texts)
    reference = two_path_scan("referenced")
    fig = maps_figure(reference, correct_scan(reference, pixelwise, CorrectionOptions(gate="all")))
    titles = [ax.get_title() for ax in fig.axes]
    assert {"raw error [mm]", "corrected error [mm]"} <= set(titles)
    assert any(t.startswith("applied correction [mm]") for t in titles)


def test_point_cloud_view_3d__decimated_to_the_limit():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(300, 300, 3)) + np.array([0.0, 0.0, 3.0])
    points[0, :5] = np.nan
    markup = point_cloud_view_3d(points, points + 0.01, rng.normal(size=(300, 300)), limit=VIEW_3D_POINTS // 4)
    assert markup.lstrip().startswith("<div") and "<html" not in markup and "Plotly.newPlot" in markup
    assert f"{VIEW_3D_POINTS // 4:,} of each" in markup
    assert len(markup) < 1_000_000
