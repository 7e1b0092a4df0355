"""The S3-compatible server of the object-store tests: moto's, on a free port of 127.0.0.1, one per session.

:func:`s3_server` points the standard AWS variables at it for the tests of one module (and puts them back
afterwards), so each module's tests, and the Dask workers they start, reach it as a user's would reach a bucket.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from benchmarks.object_storage import aws_environment
from tests.moto_server import moto_server

SECRET = "p@ss:w/rd+S3cr3t"  # the secret access key: '@', ':' and '/' in it
KEY_ID = "AKIAMPILIDARTEST"
BUCKET = "archive"


@pytest.fixture(scope="session")
def moto_endpoint() -> Iterator[str]:
    """moto's S3 server in a thread of this process, on a free port of 127.0.0.1: its endpoint URL."""
    with moto_server() as endpoint:
        yield endpoint


@pytest.fixture(scope="module")
def s3_server(moto_endpoint: str) -> Iterator[str]:
    """The server's endpoint, with the standard AWS variables pointing at it and the bucket :data:`BUCKET`
    there, for the module's tests."""
    from mpi_lidar.locations import location
    from mpi_lidar.storage import objects

    with aws_environment(moto_endpoint, KEY_ID, SECRET):
        fs = objects.filesystem(location(f"s3://{BUCKET}"))
        if not fs.exists(BUCKET):
            fs.mkdir(BUCKET)
        yield moto_endpoint


def versioned_bucket(name: str) -> str:
    """Create a bucket that keeps every version of every object (so a test can count how often one was
    written); its name."""
    import boto3

    client = boto3.client("s3")
    client.create_bucket(Bucket=name)
    client.put_bucket_versioning(Bucket=name, VersioningConfiguration={"Status": "Enabled"})
    return name


def versions_written(bucket: str, key: str) -> int:
    """How many times the object ``key`` was written in a versioned bucket (deletions not counted)."""
    import boto3

    listing = boto3.client("s3").list_object_versions(Bucket=bucket, Prefix=key)
    return sum(1 for version in listing.get("Versions", []) if version["Key"] == key)
