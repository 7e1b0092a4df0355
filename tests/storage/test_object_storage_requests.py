"""Requests of listing and unpublishing a folder in a bucket (moto's S3 server on 127.0.0.1, the requests counted
as the benchmark counts them, refused ones too)."""

from __future__ import annotations

import pytest

from benchmarks.object_storage import OPERATIONS, install_counters, take_counters
from mpi_lidar.locations import location
from mpi_lidar.storage import objects
from mpi_lidar.storage.manifest import MANIFEST_FILE
from tests.storage.conftest import BUCKET

pytestmark = pytest.mark.integration


def requests_of(action) -> dict[str, int]:
    install_counters()
    take_counters()
    action()
    return {name: int(n) for name, n in take_counters().items() if name in OPERATIONS}


@pytest.fixture
def folders(s3_server) -> str:
    """``scan1/`` with a manifest and two outputs, and ``scan10/`` beside it (its name begins with the other's)."""
    root = f"{BUCKET}/requests"
    fs = objects.filesystem(location(f"s3://{root}"))
    for key in (f"scan1/{MANIFEST_FILE}", "scan1/corrected.zarr/zarr.json", "scan1/report.md", "scan10/report.md"):
        fs.pipe_file(f"{root}/{key}", b"{}")
    return f"s3://{root}"


def test_list_files__one_listing_whether_or_not_the_folder_holds_objects(folders):
    """A folder not yet written is one LIST too (s3fs's find would then ask whether its name is an object: a HEAD
    and a second LIST, for every scan of a new batch); a folder whose name begins another's lists its own."""
    listed: list[dict[str, int]] = []
    asked = requests_of(lambda: listed.append(objects.list_files(location(f"{folders}/scan2"))))
    assert listed == [{}] and asked == {"ListObjectsV2": 1}, asked
    asked = requests_of(lambda: listed.append(objects.list_files(location(f"{folders}/scan1"))))
    assert sorted(listed[1]) == sorted([MANIFEST_FILE, "corrected.zarr/zarr.json", "report.md"])
    assert asked == {"ListObjectsV2": 1}, asked


def test_remove_prefix__nothing_asked_to_delete_where_nothing_is(folders):
    """A new folder costs its listing alone; a published one loses its manifest (one DELETE), then the rest (one
    bulk DELETE), and the folder beside it keeps its objects."""
    assert requests_of(lambda: objects.remove_prefix(location(f"{folders}/scan2"))) == {"ListObjectsV2": 1}
    asked = requests_of(lambda: objects.remove_prefix(location(f"{folders}/scan1")))
    assert asked == {"ListObjectsV2": 1, "DeleteObject": 1, "DeleteObjects": 1}, asked
    assert objects.list_files(location(f"{folders}/scan1")) == {}
    assert list(objects.list_files(location(f"{folders}/scan10"))) == ["report.md"]
