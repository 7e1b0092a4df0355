"""The options of a batch correction: those of every scan (:class:`~mpi_lidar.correction.CorrectionOptions`) and
those of the batch (:class:`BatchOptions`), declared once for ``mpi-lidar correct`` and the correction flow.

Both take them by the same names (:data:`~mpi_lidar.correction.options.USER_OPTIONS`, :data:`BATCH_OPTIONS`) and
check them here, with the same one-line error, before any scan is read.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Final

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, WithJsonSchema

from mpi_lidar.config import describe_validation_error
from mpi_lidar.correction.options import FAIL_ON, USER_OPTIONS, CorrectionOptions, ScanStatus, UserOption
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.reporting.output_levels import DEFAULT_OUTPUTS, OUTPUT_LEVELS, OutputLevel, level_files
from mpi_lidar.scans.pointcloud import PointCloudFormat, PointCloudFrame


def _fails_a_batch(status: ScanStatus) -> ScanStatus:
    if status not in FAIL_ON:
        raise ValueError(f"choose from {', '.join(FAIL_ON)}")
    return status


# A status that --fail-on names (FAIL_ON): its schema lists those alone.
FailOn = Annotated[ScanStatus, AfterValidator(_fails_a_batch),
                   WithJsonSchema({"type": "string", "enum": [status.value for status in FAIL_ON]})]


def _level_files_said() -> str:
    """Each output level's files beyond the level below it, from the registry (:data:`OUTPUT_FILES`)."""
    said: list[str] = []
    below: set[str] = set()
    for level in reversed(OUTPUT_LEVELS):  # from the least
        added = [file.name for file in level_files(level) if file.name not in below]
        full = level == OutputLevel.FULL
        added += ["a 3-D view in report.html"] if full else []
        names = ", ".join(added[:-1]) + f" and {added[-1]}" if len(added) > 1 else added[0]
        said.append(f"{'also ' if below else ''}{names} ({level}{', several times slower' if full else ''})")
        below |= set(added)
    return "; ".join(said)


# The farthest a no-return pixel may be placed [m]: beyond any AMCW scanner's ambiguity range.
MAX_NO_RETURN_RANGE_M = 1000.0


class BatchOptions(BaseModel):
    """What a batch correction does beyond each scan's options: where it runs, what each scan writes, what fails it.

    None of them is part of a corrected scan's identity.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    sensor: Path | None = Field(None, description=(
        "Sensor profile (sensor.toml from mpi-lidar calibrate): your sensor's footprint, amplitude unit, saturation "
        "and no-return thresholds, and the noise and frequency offsets it measured; --footprint-area-m2 and "
        "--amplitude-scale override its own."))
    fail_on: tuple[FailOn, ...] = Field((), description=(
        "Fail the batch (exit 1) after writing the summary when a scan has this status; repeatable. A failed scan "
        "always does, and an unserved one unless --allow-unserved."))
    allow_unserved: bool = Field(False, description=(
        "Do not fail the batch when the model cannot serve a scan (status unserved: out of its range, amplitudes in "
        "another unit, no geometry for a geometric model); its outputs keep the pixels as measured."))
    outputs: OutputLevel = Field(OutputLevel(DEFAULT_OUTPUTS), description=(
        f"What each scan writes: {_level_files_said()}. A scan already corrected at a lower level is corrected "
        "again to add the rest."))
    point_clouds: tuple[PointCloudFormat, ...] | None = Field(None, description=(
        "Write the corrected point cloud in this format at any --outputs level; repeatable: corrected.las / "
        "corrected.laz (LAS 1.4, the raw range an extra dimension) or raw.ply and corrected.ply, each with named "
        "fields per point. Default: laz at light, ply and laz at full, none at data."))
    point_cloud_frame: PointCloudFrame = Field(PointCloudFrame.SCANNER, description=(
        "Axes of the point clouds' coordinates: scanner (x to the scanner's left, y up, z forward) or z-up (x "
        "forward, y to the left, z up, as most point-cloud viewers expect); both right-handed, the scanner at the "
        "origin."))
    no_return_range_m: float | None = Field(None, gt=0, le=MAX_NO_RETURN_RANGE_M, description=(
        "Keep pixels without a range (no return, not finite, beyond the ambiguity) in the LAS/LAZ files, on their "
        "ray at this range and classified Withheld (raw_range_m keeps what was measured); by default they are "
        "left out."))
    replace_options: bool = Field(False, description=(
        "Correct into an --out that holds scans corrected with other options (or point-cloud settings): the "
        "scans of this batch get the new ones, the others keep theirs, and the summary says which made each. "
        "Without it such a batch is refused before anything is written."))
    workers: int = Field(0, ge=0, description=(
        "Worker processes of a local Dask cluster, each correcting scans of its own: for a machine with many more "
        "cores than one process keeps busy. 0: this process, which puts every core on each scan (on 2 cores "
        "1.2-1.5 times as fast as 2 workers)."))
    scheduler: str | None = Field(None, description="Address of a running Dask scheduler (tcp://host:8786).")

    def point_cloud_formats(self) -> tuple[str, ...] | None:
        """The point-cloud formats asked for, as names (None: the output level's own)."""
        return None if self.point_clouds is None else tuple(fmt.value for fmt in self.point_clouds)

    def point_cloud_placement(self) -> dict[str, Any]:
        """Where the point clouds' points lie, as :func:`~mpi_lidar.workflows.correct_archive.correct_archive`
        takes it: ``point_cloud_frame`` and ``no_return_range_m``."""
        return {"point_cloud_frame": self.point_cloud_frame.value, "no_return_range_m": self.no_return_range_m}


# BatchOptions' fields as options of `mpi-lidar correct` and parameters of the correction flow, in that order.
BATCH_OPTIONS: Final = (
    UserOption("sensor", "sensor"),
    UserOption("fail_on", "fail_on"),
    UserOption("allow_unserved", "allow_unserved"),
    UserOption("outputs", "outputs"),
    UserOption("point_clouds", "point_clouds", spelling="--point-cloud"),
    UserOption("point_cloud_frame", "point_cloud_frame"),
    UserOption("no_return_range_m", "no_return_range", unit="m", metavar="M"),
    UserOption("replace_options", "replace_options"),
    UserOption("workers", "workers"),
    UserOption("scheduler", "scheduler"),
)


def batch_options(given: Mapping[str, object]) -> tuple[CorrectionOptions, BatchOptions]:
    """The options of a batch from the values of ``mpi-lidar correct``'s options or the correction flow's
    parameters, by name; one not given, or None, keeps its default.

    A sensor profile (``sensor``) is read here, and the options given override its own. A value out of its
    bounds raises :class:`~mpi_lidar.errors.MpiLidarError` with one line naming it.
    """
    from mpi_lidar.calibration.profile import profile_options

    values = {option.field: given[option.name] for option in BATCH_OPTIONS if given.get(option.name) is not None}
    try:
        batch = BatchOptions.model_validate(values)
    except ValidationError as exc:
        problems = describe_validation_error(exc, "options", shown=None)
        raise MpiLidarError(f"invalid batch options ({problems})") from None
    correction: dict[str, Any] = {option.name: given.get(option.name) for option in USER_OPTIONS}  # from_cli checks
    model = given.get("model")  # the model directory, where given: a profile's frequencies must be its own
    checked = model if isinstance(model, str | Path) else None
    return CorrectionOptions.from_cli(**correction, **profile_options(batch.sensor, checked)), batch
