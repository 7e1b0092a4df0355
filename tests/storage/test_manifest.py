"""The manifest of an output directory: every file listed with its size and SHA-256, and each checked."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from mpi_lidar.reporting.report import REPORT_MARKER
from mpi_lidar.storage.integrity import IntegrityError
from mpi_lidar.storage.manifest import MANIFEST_FILE, is_output_directory, verify_manifest, write_manifest

pytestmark = pytest.mark.unit


@pytest.fixture
def outputs(tmp_path) -> Path:
    directory = tmp_path / "scan"
    (directory / "store.zarr" / "depth" / "c").mkdir(parents=True)
    (directory / "store.zarr" / "depth" / "c" / "0").write_bytes(b"\x01\x02\x03" * 100)
    (directory / "metrics.json").write_text('{"mae_mm": 4.741}\n')
    (directory / "report.md").write_text("# report\n")
    return directory


def test_manifest__is_the_marker_of_scan_outputs():
    assert MANIFEST_FILE == REPORT_MARKER, "the reports' marker file holds the manifest"


def test_write_manifest__lists_every_file_but_itself(outputs):
    files = write_manifest(outputs)
    assert sorted(files) == ["metrics.json", "report.md", "store.zarr/depth/c/0"]
    assert files["store.zarr/depth/c/0"]["bytes"] == 300
    assert verify_manifest(outputs) == sorted(files)
    assert is_output_directory(outputs)
    (outputs / "added.txt").write_text("a user's note")  # not listed, not checked
    assert verify_manifest(outputs) == sorted(files)


def test_verify_manifest__same_size_edit_is_caught_by_its_digest(outputs):
    write_manifest(outputs)
    (outputs / "metrics.json").write_text('{"mae_mm": 0.001}\n')  # as many bytes as before
    with pytest.raises(IntegrityError, match=r"metrics\.json is not the file written there"):
        verify_manifest(outputs)


@pytest.mark.parametrize("harm", ["deleted", "truncated", "linked", "fifo"])
def test_verify_manifest__a_listed_file_harmed_is_named(outputs, harm):
    write_manifest(outputs)
    chunk = outputs / "store.zarr" / "depth" / "c" / "0"
    if harm == "deleted":
        chunk.unlink()
    elif harm == "truncated":
        chunk.write_bytes(chunk.read_bytes()[:7])
    elif harm == "linked":
        chunk.unlink()
        chunk.symlink_to("/dev/zero")
    else:
        chunk.unlink()
        os.mkfifo(chunk)
    with pytest.raises(IntegrityError, match=r"store\.zarr/depth/c/0"):
        verify_manifest(outputs)


@pytest.mark.parametrize("content", ["", "{not json", json.dumps({"schema": "other", "files": {}}),
                                     json.dumps({"schema": "mpi-lidar/outputs-manifest@1",
                                                 "files": {"../../etc/passwd": {"bytes": 1, "sha256": "0" * 64}}}),
                                     json.dumps({"schema": "mpi-lidar/outputs-manifest@1",
                                                 "files": {"report.md": {"bytes": "9", "sha256": "0" * 64}}})])
def test_verify_manifest__empty_or_malformed_manifest_trusts_nothing(outputs, content):
    (outputs / MANIFEST_FILE).write_text(content)
    with pytest.raises(IntegrityError, match="manifest"):
        verify_manifest(outputs)


def test_verify_manifest__no_manifest_at_all(outputs):
    assert not is_output_directory(outputs)
    with pytest.raises(IntegrityError, match="cannot be read"):
        verify_manifest(outputs)


def test_atomic_path__a_marked_directory_is_published_with_its_manifest(tmp_path):
    from mpi_lidar.storage.atomic import atomic_path

    target = tmp_path / "scan"
    with atomic_path(target, replace=True) as staging:
        staging.mkdir()
        (staging / "metrics.json").write_text("{}")
        (staging / MANIFEST_FILE).write_text("")  # the outputs' marker, empty: sealed at publication
    assert verify_manifest(target) == ["metrics.json"]
    with pytest.raises(RuntimeError), atomic_path(target, replace=True) as staging:
        staging.mkdir()
        (staging / MANIFEST_FILE).write_text("")
        raise RuntimeError("interrupted")
    assert verify_manifest(target) == ["metrics.json"], "the outputs in place are kept whole"
    with atomic_path(tmp_path / "plain", replace=True) as staging:  # no marker: nothing added
        staging.mkdir()
        (staging / "a.txt").write_text("a")
    assert sorted(p.name for p in (tmp_path / "plain").iterdir()) == ["a.txt"]
