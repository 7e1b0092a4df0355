"""Which point-cloud files a scan's outputs hold, by output level and as asked, and their fields."""

from __future__ import annotations

from pathlib import Path

import laspy
import pytest

from mpi_lidar.cli.correct import correct as correct_command
from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.reporting.cloud_figures import PLOTLY_JS
from mpi_lidar.reporting.output_levels import DEFAULT_OUTPUTS, OutputLevel
from mpi_lidar.reporting.point_cloud_files import (
    FULL_POINT_CLOUDS,
    LEVEL_POINT_CLOUDS,
    POINT_CLOUD_FILES,
    point_cloud_formats,
)
from mpi_lidar.scans.pointcloud import POINT_CLOUD_FORMATS, PointCloudFormat
from mpi_lidar.workflows.correct_archive import correct_archive, process_scan

pytestmark = pytest.mark.unit

FIELDS = {"raw_range_m", "corrected_range_m", "correction_mm", "flag", "amplitude_v2", "row", "column"}


def test_point_cloud_format__one_closed_set():
    assert POINT_CLOUD_FORMATS == ("las", "laz", "ply") == tuple(PointCloudFormat)
    assert set(POINT_CLOUD_FILES) == set(PointCloudFormat) and FULL_POINT_CLOUDS == ("ply", "laz")
    assert set(LEVEL_POINT_CLOUDS) == set(OutputLevel) and LEVEL_POINT_CLOUDS[OutputLevel.FULL] == FULL_POINT_CLOUDS
    # a level holds what the next one holds (each format once); the default level writes the LAZ
    assert set(LEVEL_POINT_CLOUDS["light"]) <= set(LEVEL_POINT_CLOUDS["full"]) and LEVEL_POINT_CLOUDS["data"] == ()
    assert point_cloud_formats(DEFAULT_OUTPUTS) == LEVEL_POINT_CLOUDS[OutputLevel(DEFAULT_OUTPUTS)]
    option = next(p for p in correct_command.params if p.name == "point_clouds")
    assert tuple(option.type.choices) == POINT_CLOUD_FORMATS, "the command line offers every format"


def test_light__the_laz_by_default_and_the_formats_asked_for(model_dir, archived, tmp_path):
    light = process_scan(archived[1], model_dir, tmp_path / "light", CorrectionOptions(gate="all"), outputs="light")
    names = {p.name for p in Path(light.output).iterdir()}
    assert "corrected.laz" in names and not names & {"raw.ply", "corrected.ply", "corrected.las", PLOTLY_JS}
    assert set(laspy.read(Path(light.output) / "corrected.laz").point_format.extra_dimension_names) >= FIELDS
    outcomes = correct_archive([str(archived[1])], model_dir, tmp_path / "asked", CorrectionOptions(gate="all"),
                               outputs="light", point_clouds=("las",))
    names = {p.name for p in Path(outcomes[0].output).iterdir()}
    assert "corrected.las" in names and not names & {"raw.ply", "corrected.ply", "corrected.laz", PLOTLY_JS}
    # the light outputs exist, but without the PLY files asked for now: corrected again to add them
    again = process_scan(archived[1], model_dir, tmp_path / "light", CorrectionOptions(gate="all"), outputs="light",
                         point_clouds=("ply",))
    assert again.status == "corrected" and (Path(again.output) / "corrected.ply").is_file()
    assert process_scan(archived[1], model_dir, tmp_path / "light", CorrectionOptions(gate="all"),
                        outputs="light", point_clouds=("ply",)).status == "skipped"


def test_point_cloud_formats__default_by_level_and_unknown_refused(model_dir, archived, tmp_path):
    assert point_cloud_formats("full") == ("ply", "laz") and point_cloud_formats("light") == ("laz",)
    assert point_cloud_formats("data", ["laz", "ply", "laz"]) == ("ply", "laz")
    assert point_cloud_formats("full", ()) == ()
    with pytest.raises(MpiLidarError, match="unknown point cloud format 'xyz'"):
        correct_archive([str(archived[1])], model_dir, tmp_path / "out", CorrectionOptions(), point_clouds=["xyz"])
    assert not (tmp_path / "out").exists(), "refused before anything is written"


@pytest.mark.parametrize("amplitude_scale", [4000.0])
def test_light__amplitudes_in_the_scanners_unit_reach_the_laz_in_v2(model_dir, archived, tmp_path, amplitude_scale):
    """A scan in counts (4000 per V^2), its unit given: the LAZ's amplitude_v2 is the V^2 amplitude."""
    from dataclasses import replace

    import numpy as np

    from mpi_lidar.scans.store import write_scan

    scan = archived[0]
    counts = write_scan(replace(scan, amplitude=(np.asarray(scan.amplitude) * 4000).astype(np.float32)),
                        tmp_path / "counts.scan.zarr")
    outcome = process_scan(counts, model_dir, tmp_path / "out", CorrectionOptions(amplitude_scale=amplitude_scale),
                           outputs="light")
    las = laspy.read(Path(outcome.output) / "corrected.laz")
    expected = np.asarray(scan.amplitude[-1])[np.asarray(las.row), np.asarray(las.column)]
    np.testing.assert_allclose(np.asarray(las.amplitude_v2), expected, rtol=1e-6)
