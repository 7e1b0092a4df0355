"""A re-run verifies what it skips, and ``verify`` checks a scan's outputs whole: every file their manifest
lists, and ``corrected.zarr`` chunk by chunk against fingerprints it must have.

Outputs are written by the project's own batch correction (a tiny model trained here) and damaged by
deleting, editing or replacing their files.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tracemalloc
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.scans.store import write_scan
from mpi_lidar.storage.integrity import IntegrityError
from mpi_lidar.storage.manifest import MANIFEST_FILE, verify_manifest
from mpi_lidar.workflows.correct_archive import correct_archive
from mpi_lidar.workflows.verify import verify_store
from tests.cli_runner import assert_one_error_line, call_main
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

OPTIONS = CorrectionOptions(gate="all")


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    return tiny_model(tmp_path_factory.mktemp("model") / "model")


@pytest.fixture(scope="module")
def corrected(tmp_path_factory, model) -> tuple[Path, Path]:
    """(scans directory, output directory) of one scan ``a`` corrected at level light."""
    root = tmp_path_factory.mktemp("outputs")
    write_scan(two_path_scan("a"), root / "scans" / "a.scan.zarr")
    [outcome] = correct_archive([str(root / "scans")], model, root / "out", OPTIONS, outputs="light")
    assert outcome.status == "corrected"
    return root / "scans", root / "out"


def copied(corrected: tuple[Path, Path], tmp_path: Path) -> tuple[Path, Path]:
    scans, out = corrected
    shutil.copytree(out, tmp_path / "out")
    return scans, tmp_path / "out"


def corrected_depth_chunk(output: Path) -> Path:
    [chunk] = sorted(p for p in (output / "corrected.zarr" / "corrected_depth" / "c").rglob("*") if p.is_file())
    return chunk


def delete_chunk(output: Path) -> None:
    corrected_depth_chunk(output).unlink()


def flatter_metrics(output: Path) -> None:
    """metrics.json still valid JSON, its corrected MAE made 0.001 mm, as a careless edit would."""
    path = output / "metrics.json"
    data = json.loads(path.read_text())
    for region in data["metrics"].values():
        for key in region:
            if "corrected" in key and "mae" in key:
                region[key] = 0.001
    path.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")


def delete_thumbnail(output: Path) -> None:
    (output / "thumbnail.png").unlink()


def edit_report(output: Path) -> None:
    path = output / "report.md"
    path.write_text(path.read_text().replace("|", "!", 1))


def link_chunk(output: Path) -> None:
    chunk = corrected_depth_chunk(output)
    shutil.copyfile(chunk, output.parent / "elsewhere")  # the same bytes, but through a link
    chunk.unlink()
    chunk.symlink_to(output.parent / "elsewhere")


def empty_manifest(output: Path) -> None:
    (output / MANIFEST_FILE).write_text("")


DAMAGES = {"corrected_depth chunk deleted": (delete_chunk, "corrected_depth/c/0/0 is missing"),
           "metrics.json edited": (flatter_metrics, "metrics.json"),
           "thumbnail.png deleted": (delete_thumbnail, "thumbnail.png is missing"),
           "report.md edited": (edit_report, "report.md is not the file written there"),
           "chunk replaced by a link": (link_chunk, "is a symbolic link"),
           "manifest emptied": (empty_manifest, "have no manifest")}


@pytest.mark.unit
def test_rerun__intact_outputs_are_verified_then_skipped(model, corrected, tmp_path):
    scans, out = copied(corrected, tmp_path)
    listed = verify_manifest(out / "a")
    assert {"metrics.json", "report.md", "report.html", "thumbnail.png", "corrected.zarr/zarr.json"} <= set(listed)
    assert any(name.startswith("corrected.zarr/corrected_depth/c/") for name in listed), "chunks are listed"
    [again] = correct_archive([str(scans)], model, out, OPTIONS, outputs="light")
    assert again.status == "skipped" and again.counts["corrected"] > 0
    assert verify_store(out / "a").files == len(listed)


@pytest.mark.unit
@pytest.mark.parametrize("damage", sorted(DAMAGES))
def test_rerun__damaged_outputs_are_corrected_again_not_skipped(model, corrected, tmp_path, damage):
    scans, out = copied(corrected, tmp_path)
    before = json.loads((out / "a" / "metrics.json").read_text())
    harm, why = DAMAGES[damage]
    harm(out / "a")
    with pytest.raises(IntegrityError, match=re.escape(why)):
        verify_store(out / "a")
    [again] = correct_archive([str(scans)], model, out, OPTIONS, outputs="light")
    assert again.status == "corrected", "damage is redone, not reported as skipped"
    assert any("existing outputs were damaged" in note for note in again.notes)
    assert json.loads((out / "a" / "metrics.json").read_text())["metrics"] == before["metrics"]
    assert verify_store(out / "a").files > 0, "the redone outputs verify"
    [third] = correct_archive([str(scans)], model, out, OPTIONS, outputs="light")
    assert third.status == "skipped"


@pytest.mark.integration
def test_correct_cli__rerun_over_a_deleted_chunk_corrects_it(model, corrected, tmp_path, monkeypatch, capsys):
    scans, out = copied(corrected, tmp_path)
    delete_chunk(out / "a")
    code, stdout, _ = call_main(monkeypatch, capsys, "correct", scans, "--model", model, "--out", out,
                                "--gate", "all")
    assert code == 0 and "1 corrected" in stdout and "1 already done" not in stdout
    assert verify_store(out / "a").chunks > 0


# --- verify of a corrected store -----------------------------------------------------------------------------


def bare_store(corrected: tuple[Path, Path], tmp_path: Path) -> Path:
    """A copy of the corrected store alone, outside its output directory (no manifest checks it first)."""
    return Path(shutil.copytree(corrected[1] / "a" / "corrected.zarr", tmp_path / "corrected.zarr"))


def edit_store_attrs(store: Path, edit) -> None:
    meta = json.loads((store / "zarr.json").read_text())
    edit(meta["attributes"])
    (store / "zarr.json").write_text(json.dumps(meta))


@pytest.mark.unit
def test_verify__corrected_store_without_fingerprints_is_damaged(corrected, tmp_path, monkeypatch, capsys):
    store = bare_store(corrected, tmp_path)
    edit_store_attrs(store, lambda attrs: attrs.pop("chunk_sha256"))
    with pytest.raises(IntegrityError, match=r"chunk fingerprints \(chunk_sha256\) are missing"):
        verify_store(store)
    code, stdout, stderr = call_main(monkeypatch, capsys, "verify", store)
    assert code == 1 and not stdout
    assert_one_error_line(stderr, "chunk_sha256")


@pytest.mark.unit
@pytest.mark.parametrize("keep_fingerprints", [True, False])
def test_verify__corrected_store_with_flags_removed_is_damaged(corrected, tmp_path, keep_fingerprints):
    store = bare_store(corrected, tmp_path)
    shutil.rmtree(store / "flags")
    if not keep_fingerprints:
        edit_store_attrs(store, lambda attrs: attrs["chunk_sha256"].pop("flags"))
    with pytest.raises(IntegrityError, match=r"'flags'.* gone"):
        verify_store(store)


@pytest.mark.unit
@pytest.mark.parametrize("chunked", [False, True])
def test_verify__declared_100000_by_100000_is_refused_before_allocating(corrected, tmp_path, chunked):
    store = bare_store(corrected, tmp_path)
    meta_path = store / "corrected_depth" / "zarr.json"
    meta = json.loads(meta_path.read_text())
    meta["shape"] = [100_000, 100_000]
    if chunked:
        meta["chunk_grid"]["configuration"]["chunk_shape"] = [100_000, 100_000]
    meta_path.write_text(json.dumps(meta))
    tracemalloc.start()
    try:
        with pytest.raises(IntegrityError, match="corrected_depth"):
            verify_store(store)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 * 2**20, f"{peak / 2**20:.0f} MiB allocated before refusing"


@pytest.mark.unit
def test_verify__the_manifest_catches_what_the_store_would_too(corrected, tmp_path):
    _, out = copied(corrected, tmp_path)
    edit_store_attrs(out / "a" / "corrected.zarr", lambda attrs: attrs.pop("chunk_sha256"))
    with pytest.raises(IntegrityError, match=r"corrected\.zarr/zarr\.json has .* bytes, not the .* written"):
        verify_store(out / "a" / "corrected.zarr")


@pytest.mark.unit
def test_verify__output_directory_with_its_store_deleted_is_damaged(corrected, tmp_path):
    _, out = copied(corrected, tmp_path)
    shutil.rmtree(out / "a" / "corrected.zarr")
    with pytest.raises(IntegrityError, match=r"corrected\.zarr/.* is missing"):
        verify_store(out / "a")
    assert not os.path.exists(out / "a" / "corrected.zarr"), "verify writes nothing"


@pytest.mark.integration
@pytest.mark.parametrize("damage", ["fingerprints removed", "depth's fingerprints removed"])
def test_correct_cli__scan_without_its_fingerprints_fails_and_writes_nothing(model, tmp_path, monkeypatch, capsys,
                                                                             damage):
    path = write_scan(two_path_scan("a"), tmp_path / "scans" / "a.scan.zarr")
    meta = json.loads((path / "zarr.json").read_text())
    if damage == "fingerprints removed":
        del meta["attributes"]["chunk_sha256"]
    else:
        del meta["attributes"]["chunk_sha256"]["depth"]
    (path / "zarr.json").write_text(json.dumps(meta))
    next(p for p in sorted((path / "depth" / "c").rglob("*")) if p.is_file()).unlink()  # would read as zeros
    code, stdout, stderr = call_main(monkeypatch, capsys, "correct", tmp_path / "scans", "--model", model,
                                     "--out", tmp_path / "out", "--gate", "all")
    assert code == 1 and "1 failed" in stdout
    assert_one_error_line(stderr, "fingerprints")
    assert not (tmp_path / "out" / "a").exists()


@pytest.mark.unit
@settings(max_examples=15, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(harms=st.lists(st.tuples(st.sampled_from(["delete", "append", "flip", "empty"]), st.integers(0, 10**6)),
                      min_size=1, max_size=2))
def test_rerun__any_harm_to_any_file_is_redone_or_skipped_intact(model, corrected, tmp_path_factory, harms):
    """Whatever happens to the outputs' files, a re-run never reports them as done unless they are as written."""
    scans, out = copied(corrected, tmp_path_factory.mktemp("harm"))
    before = json.loads((out / "a" / "metrics.json").read_text())
    for how, pick in harms:
        files = sorted(p for p in (out / "a").rglob("*") if p.is_file() and p.name != MANIFEST_FILE)
        if not files:
            continue
        target = files[pick % len(files)]
        if how == "delete":
            target.unlink()
        elif how == "append":
            target.write_bytes(target.read_bytes() + b"\0")
        elif how == "flip" and target.stat().st_size:
            data = bytearray(target.read_bytes())
            data[pick % len(data)] ^= 0x01
            target.write_bytes(bytes(data))
        elif how == "empty":
            target.write_bytes(b"")
    [again] = correct_archive([str(scans)], model, out, OPTIONS, outputs="light")
    assert again.status in ("skipped", "corrected")
    assert verify_store(out / "a").files > 0, "what is left after the re-run is whole"
    assert json.loads((out / "a" / "metrics.json").read_text())["metrics"] == before["metrics"]
    assert again.metrics == before["metrics"]
