"""Paths and object-store URLs parsed once, and never shown with a credential."""

from __future__ import annotations

from pathlib import Path

import pytest

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.locations import Location, display_url, is_url, location

pytestmark = pytest.mark.unit

PASSWORD = "p@ss:w/rd"


def test_location__plain_path_is_local():
    place = location("scans/day1")
    assert place.is_local and place.local_path() == Path("scans/day1")
    assert place.joinpath("a.scan.zarr").local_path() == Path("scans/day1/a.scan.zarr")


def test_location__file_url_is_local():
    assert location("file:///data/scans") == Location("", "/data/scans")


@pytest.mark.parametrize("url", ["s3://bucket/scans/", "s3://bucket//scans", "s3a://bucket/scans"])
def test_location__s3_url_normalised(url):
    place = location(url)
    assert not place.is_local and place.url == "s3://bucket/scans"
    assert place.joinpath("day1/a.scan.zarr").url == "s3://bucket/scans/day1/a.scan.zarr"
    assert place.name == "scans" and place.parent.url == "s3://bucket"


def test_location__path_with_at_sign_is_kept():
    assert location("s3://bucket/a/b@c").url == "s3://bucket/a/b@c"


@pytest.mark.parametrize("url", [f"s3://AKIAEXAMPLE:{PASSWORD}@bucket/scans", f"gs://user:{PASSWORD}@bucket/x"])
def test_location__credential_in_url_refused_masked(url):
    with pytest.raises(MpiLidarError) as error:
        location(url)
    message = str(error.value)
    assert "credential" in message and "***" in message
    assert PASSWORD not in message and "ss:w/rd" not in message and "p@ss" not in message


def test_location__unknown_scheme_refused():
    with pytest.raises(MpiLidarError, match="not a store"):
        location("ftp://host/x")


def test_location__bucket_required():
    with pytest.raises(MpiLidarError, match="names no bucket"):
        location("s3://")


def test_display_url__scheduler_and_database_passwords_masked():
    for url in (f"tcp://user:{PASSWORD}@10.0.0.1:8786", f"postgresql+psycopg://user:{PASSWORD}@db/optuna"):
        shown = display_url(url)
        assert PASSWORD not in shown and "***" in shown and is_url(url)
    assert not is_url("scans/a.scan.zarr")
