"""One scan's outputs: each output level's files, the full outputs of an archived scan (maps, named point
clouds, the interactive 3-D view), and nothing of pyplot's global state touched on the way."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import laspy
import matplotlib.image
import numpy as np
import pytest
from plyfile import PlyData

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.reporting.cloud_figures import PLOTLY_JS, VIEW_3D_FALLBACK
from mpi_lidar.reporting.output_levels import DEFAULT_OUTPUTS, OUTPUT_LEVELS, OutputLevel, covers
from mpi_lidar.reporting.thumbnail import FLAG_COLOURS, KEY_ROW_PX
from mpi_lidar.scans.store import write_scan
from mpi_lidar.simulation.scenes import cornered_board, render
from mpi_lidar.workflows.correct_archive import process_scan

FIELDS = {"raw_range_m", "corrected_range_m", "correction_mm", "flag", "amplitude_v2", "row", "column"}


@pytest.fixture(scope="module")
def full_run(model_dir, archived, tmp_path_factory):
    """The archived scan's full outputs, written while a user's pyplot figure is open: the outcome, the user's
    figure number, whether it was still open afterwards and the numbers of every figure open then."""
    import matplotlib.pyplot as plt

    mine = plt.figure()
    try:
        outcome = process_scan(archived[1], model_dir, tmp_path_factory.mktemp("out"), CorrectionOptions(gate="all"),
                               outputs="full")
        return outcome, mine.number, plt.fignum_exists(mine.number), plt.get_fignums()
    finally:
        plt.close(mine)


@pytest.fixture(scope="module")
def full_outputs(full_run) -> Path:
    outcome = full_run[0]
    assert outcome.status == "corrected", outcome.reason
    return Path(outcome.output)


@pytest.fixture(scope="module")
def level_outputs(model_dir, board_store, tmp_path_factory):
    """The board's outputs at a level (written once per level, each into a directory of its own)."""
    outcomes = {}

    def written(level: str):
        if level not in outcomes:
            outcomes[level] = process_scan(board_store, model_dir, tmp_path_factory.mktemp(level), CorrectionOptions(),
                                           outputs=level)
        return outcomes[level]

    return written


@pytest.mark.slow
@pytest.mark.integration
def test_full__archived_scan_writes_maps_named_point_clouds_and_the_3d_view(full_outputs, archived):
    scan = archived[0]
    names = {p.name for p in full_outputs.iterdir()}
    assert {"maps.png", "point_cloud.png", "raw.ply", "corrected.ply", "corrected.laz"} <= names
    assert PLOTLY_JS not in names, "one plotly.js per batch, in the folder above the scans' own"
    assert "error_hist.png" not in names
    raw, corrected = (PlyData.read(str(full_outputs / name))["vertex"] for name in ("raw.ply", "corrected.ply"))
    assert {p.name for p in corrected.properties} == ({"x", "y", "z", "red", "green", "blue"}
                                                      | {f"scalar_{f}" for f in FIELDS | {"uncertainty_m"}})
    assert raw.count == corrected.count > 0
    # the raw cloud lies at the raw range, the corrected one at the corrected range, pixel by pixel
    row, column = np.asarray(corrected["scalar_row"]), np.asarray(corrected["scalar_column"])
    for cloud, field in ((raw, "scalar_raw_range_m"), (corrected, "scalar_corrected_range_m")):
        radius = np.sqrt(np.asarray(cloud["x"], float) ** 2 + np.asarray(cloud["y"], float) ** 2
                         + np.asarray(cloud["z"], float) ** 2)
        np.testing.assert_allclose(radius, np.asarray(cloud[field], float), atol=1e-5)
    np.testing.assert_allclose(np.asarray(raw["scalar_raw_range_m"]), scan.depth[-1][row, column])
    las = laspy.read(full_outputs / "corrected.laz")
    assert str(las.header.version) == "1.4" and len(las.points) == corrected.count
    assert set(las.point_format.extra_dimension_names) >= FIELDS
    np.testing.assert_allclose(np.asarray(las["raw_range_m"]), scan.depth[-1][las["row"], las["column"]])
    html = (full_outputs / "report.html").read_text()
    assert 'class="plotly-graph-div"' in html and f'<script src="../{PLOTLY_JS}"></script>' in html
    assert "cdn.plot.ly" not in html and "https://" not in html.split("<body>")[0], "no CDN: archives are offline"
    assert (full_outputs.parent / PLOTLY_JS).stat().st_size > 1_000_000
    assert VIEW_3D_FALLBACK in (full_outputs / "report.md").read_text()
    files = json.loads((full_outputs / "metrics.json").read_text())["outputs"]["files"]
    assert {"corrected.laz", "raw.ply", "corrected.ply"} <= set(files) and PLOTLY_JS not in files


# --- output levels ----------------------------------------------------------------------------------------

FILES = {
    "data": {"corrected.zarr", "metrics.json"},
    "light": {"corrected.zarr", "metrics.json", "report.md", "report.html", "thumbnail.png", "corrected.laz"},
    "full": {"corrected.zarr", "metrics.json", "report.md", "report.html", "maps.png", "error_hist.png",
             "point_cloud.png", "raw.ply", "corrected.ply", "corrected.laz", "thumbnail.png"},
}
GEOMETRY_FILES = {"point_cloud.png", "raw.ply", "corrected.ply", "corrected.laz"}


def _listing(path: Path) -> set[str]:
    return {p.name for p in path.iterdir() if not p.name.startswith(".")}


@pytest.mark.unit
def test_output_level__one_closed_set_from_most_to_least():
    assert OUTPUT_LEVELS == ("full", "light", "data") == tuple(OutputLevel)


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.parametrize("level", OUTPUT_LEVELS)
def test_write_scan_outputs__each_level_writes_its_files_and_says_which(level, level_outputs):
    outcome = level_outputs(level)
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


@pytest.mark.unit
def test_thumbnail__written_at_level_light_with_its_legend(level_outputs):
    outcome = level_outputs("light")
    image = matplotlib.image.imread(Path(outcome.output) / "thumbnail.png")
    # a small scan (40 x 56) is shown 4 times its size (each panel at most 254 pixels wide), over a colour key with
    # a line per few flags
    assert image.shape[1] == 2 * 4 * 56 + 4 and image.shape[0] > 4 * 40 + 2 * KEY_ROW_PX
    flags = np.asarray(image[4 * 40:, :, :3] * 255).round().astype(int).reshape(-1, 3)
    swatch = tuple(int(FLAG_COLOURS[0][i:i + 2], 16) for i in (1, 3, 5))
    assert (flags == swatch).all(axis=1).any(), "the key shows the corrected flag's colour"
    report = (Path(outcome.output) / "report.md").read_text()
    assert "Thumbnail: corrected depth (left" in report and "#" not in report.split("Thumbnail:")[1].split("\n")[0]


@pytest.mark.integration
@pytest.mark.slow
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


@pytest.mark.integration
@pytest.mark.slow
def test_output_level__scan_without_geometry_says_point_clouds_were_skipped(pixelwise_model, tmp_path):
    scan = render(cornered_board(height=24, width=32), Config(), np.random.default_rng(1))
    store = write_scan(replace(scan, azimuth_rad=None, elevation_rad=None), tmp_path / "flat.scan.zarr")
    pixelwise = pixelwise_model
    outcome = process_scan(store, pixelwise, tmp_path / "out", CorrectionOptions(), outputs="full")
    assert "no scan geometry: point clouds and views skipped" in outcome.notes
    assert _listing(Path(outcome.output)) == FILES["full"] - GEOMETRY_FILES
    light = process_scan(store, pixelwise, tmp_path / "light", CorrectionOptions(), outputs="light")
    assert "no scan geometry: point clouds skipped" in light.notes
    assert _listing(Path(light.output)) == FILES["light"] - GEOMETRY_FILES


@pytest.mark.unit
def test_output_level__unknown_level_is_one_clear_error(model_dir, board_store, tmp_path):
    from mpi_lidar.errors import MpiLidarError
    from mpi_lidar.workflows.correct_archive import correct_archive

    with pytest.raises(MpiLidarError, match="unknown output level 'everything'; choose one of full, light, data"):
        correct_archive([str(board_store)], model_dir, tmp_path, CorrectionOptions(), outputs="everything")
    assert not any(tmp_path.iterdir()), "refused before anything is written"


# --- no global state -----------------------------------------------------------------------------------------


@pytest.mark.integration
def test_write_scan_outputs__a_users_open_pyplot_figure_survives(full_run):
    outcome, mine, survived, open_after = full_run  # full outputs written while the user's figure was open
    assert outcome.status == "corrected", outcome.reason
    assert survived and open_after == [mine], "no figure closed or left"


@pytest.mark.integration
@pytest.mark.slow
def test_import__reporting_leaves_the_matplotlib_backend_alone():
    code = ("import matplotlib; matplotlib.use('svg'); before = matplotlib.get_backend(); "
            "import mpi_lidar.reporting.report, mpi_lidar.reporting.scan_outputs, mpi_lidar.reporting.table2, "
            "mpi_lidar.reporting.tuning_report, mpi_lidar.workflows.correct_archive; "
            "assert matplotlib.get_backend() == before == 'svg', matplotlib.get_backend(); "
            "import sys; assert 'matplotlib.pyplot' not in sys.modules, 'pyplot imported'")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
