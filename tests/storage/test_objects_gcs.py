"""Outputs published to Google Cloud Storage (gs://) with the guarantees of S3, against a real GCS server
(fake-gcs-server, started here on 127.0.0.1): the store-independent cases of test_objects_azure.py, and what
only GCS needs (its version is the generation, not the ETag)."""

from __future__ import annotations

import os
import urllib.error
import urllib.request
from collections.abc import Iterator

import pytest

from mpi_lidar.locations import location
from mpi_lidar.storage import objects
from tests.gcs_server import gcs_environment, gcs_server
from tests.storage.test_objects_azure import (
    conditional_writes_are_atomic,
    corrected_outputs_match_local,
    dataset_and_model_published,
    killed_writer_leaves_no_output,
    lock_renewed_while_held,
    second_writer_cannot_publish,
    stale_lock_taken_over_once,
)

pytestmark = pytest.mark.integration

BUCKET = "archive"


@pytest.fixture(scope="module")
def gcs_root() -> Iterator[str]:
    """fake-gcs-server running, the standard variables pointing at it and the bucket :data:`BUCKET` there, for
    the module's tests: ``gs://<bucket>``."""
    with gcs_server() as url, gcs_environment(url):
        objects.filesystem(location(f"gs://{BUCKET}")).mkdir(BUCKET)
        yield f"gs://{BUCKET}"


def test_server__refuses_a_failed_generation_precondition(gcs_root):
    """What the GCS tests rely on, asked of the server directly: a multipart upload with ifGenerationMatch=0
    over an object, or with a generation that is not the object's, is refused with 412."""
    statuses = []
    for generation in ("0", "0", "1"):
        body = (b'--b\nContent-Type: application/json\n\n{"name": "precondition"}\n--b\n'
                b"Content-Type: application/octet-stream\n\nx\n--b--")
        request = urllib.request.Request(
            f"{os.environ['STORAGE_EMULATOR_HOST']}/upload/storage/v1/b/{BUCKET}/o?uploadType=multipart"
            f"&ifGenerationMatch={generation}", data=body, headers={"Content-Type": 'multipart/related; boundary="b"'},
            method="POST")
        try:
            with urllib.request.urlopen(request) as response:
                statuses.append(response.status)
        except urllib.error.HTTPError as error:
            statuses.append(error.code)
    assert statuses == [200, 412, 412]


def test_write_object__conditional_create_and_overwrite_on_gcs(gcs_root):
    conditional_writes_are_atomic(gcs_root)


def test_write_object__version_is_the_generation(gcs_root):
    """An overwrite names the generation: a GCS ETag may be the content's hash, the same for two writes."""
    where = location(f"{gcs_root}/generation/object")
    first = objects.write_object(where, b"same", create=True)
    second = objects.write_object(where, b"same", if_match=first)
    info = objects.filesystem(where).info(where.path)
    assert first.isdigit() and second != first and str(info["generation"]) == second


def test_publish_directory__second_writer_refused_on_gcs(gcs_root, tmp_path, monkeypatch):
    second_writer_cannot_publish(gcs_root, tmp_path, monkeypatch)


def test_object_output_lock__stale_lock_taken_over_once_on_gcs(gcs_root):
    stale_lock_taken_over_once(gcs_root)


def test_object_output_lock__renewed_while_held_on_gcs(gcs_root, monkeypatch):
    lock_renewed_while_held(gcs_root, monkeypatch)


@pytest.mark.slow
def test_correct__bucket_outputs_identical_to_local_and_verified_on_gcs(gcs_root, pixelwise_model, tmp_path,
                                                                        monkeypatch, capsys, caplog):
    corrected_outputs_match_local(gcs_root, pixelwise_model, tmp_path, monkeypatch, capsys, caplog, secret=None)


@pytest.mark.slow
def test_simulate_and_train__dataset_and_model_in_bucket_on_gcs(gcs_root, tmp_path, monkeypatch, capsys):
    dataset_and_model_published(gcs_root, tmp_path, monkeypatch, capsys)


@pytest.mark.slow
def test_correct__killed_batch_on_gcs_leaves_only_whole_outputs(gcs_root, pixelwise_model, tmp_path, monkeypatch,
                                                               capsys):
    killed_writer_leaves_no_output(gcs_root, pixelwise_model, tmp_path, monkeypatch, capsys)
