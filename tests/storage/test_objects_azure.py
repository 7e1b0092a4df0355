"""Outputs published to Azure Blob Storage (az://) with the guarantees of S3, against a real Azure Blob server
(Azurite, started here on 127.0.0.1); the store-independent cases below run on GCS too (test_objects_gcs.py)."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.locations import location
from mpi_lidar.redact import install_log_redaction, redact
from mpi_lidar.scans.store import write_scan
from mpi_lidar.storage import objects
from mpi_lidar.storage.manifest import MANIFEST_FILE
from mpi_lidar.storage.publication import LOCK_FILE
from tests.azurite_server import ACCOUNT_KEY, azure_environment, azurite_server, connection_string
from tests.cli_runner import call_main
from tests.scan_factory import two_path_scan
from tests.storage.test_object_storage import PROVENANCE, TIMES, files_of, untimed

ROOT = Path(__file__).resolve().parents[2]
CONTAINER = "archive"
# An account key as a user could paste it: '@', ':' and '/' in it (Azurite's own key has '/' and '+').
ODD_KEY = "p@ss:w/rd+AzKey=="


@pytest.fixture(scope="module")
def azure_root() -> Iterator[str]:
    """Azurite running, ``AZURE_STORAGE_CONNECTION_STRING`` pointing at it and the container :data:`CONTAINER`
    there, for the module's tests: ``az://<container>``."""
    with azurite_server() as endpoint, azure_environment(endpoint):
        objects.filesystem(location(f"az://{CONTAINER}")).mkdir(CONTAINER)
        yield f"az://{CONTAINER}"


# --- what any connection string or key may meet: messages and logs ------------------------------------------------


@pytest.mark.unit
@pytest.mark.parametrize("form", [
    "{cs}",
    "error: cannot reach the store ({cs!r})",
    "AZURE_STORAGE_CONNECTION_STRING=\"{cs}\"",
    "AZURE_STORAGE_ACCOUNT_KEY={key}",
    "{{'account_name': 'acct', 'account_key': '{key}'}}",
    "https://acct.blob.core.windows.net/c/x?sv=2024-11-04&sp=r&sig={key}&se=2026-12-01",
    "SharedAccessSignature=sv=2024-11-04&sig={key};BlobEndpoint=https://acct.blob.core.windows.net",
])
def test_redact__azure_key_in_every_form_masked(form):
    text = form.format(cs=connection_string("https://acct.blob.core.windows.net", ODD_KEY), key=ODD_KEY)
    shown = redact(text)
    assert ODD_KEY not in shown and "w/rd" not in shown and "***" in shown, shown


@pytest.mark.unit
def test_redact__azure_key_in_a_log_record_masked(caplog):
    install_log_redaction()
    with caplog.at_level(logging.INFO):
        logging.getLogger("azure.test").info("connecting with %s", connection_string("http://h/acct", ODD_KEY))
    assert ODD_KEY not in caplog.text and "AccountKey=***" in caplog.text


@pytest.mark.unit
def test_location__account_in_an_abfs_url_refused_with_one_line():
    with pytest.raises(MpiLidarError) as error:
        location("abfs://scans@myaccount.dfs.core.windows.net/day1")
    assert "\n" not in str(error.value) and "give az://scans/<path>" in str(error.value)


# --- cases every writable store passes (test_objects_gcs.py runs them on GCS) ------------------------------------


def conditional_writes_are_atomic(root: str) -> None:
    """A conditional create succeeds once; an overwrite naming the version read succeeds once, one naming an older
    version is refused, and neither refusal changes the object."""
    where = location(f"{root}/conditional/object")
    first = objects.write_object(where, b"one", create=True)
    with pytest.raises(FileExistsError):
        objects.write_object(where, b"two", create=True)
    second = objects.write_object(where, b"three", if_match=first)
    assert second and second != first
    with pytest.raises(FileExistsError):
        objects.write_object(where, b"four", if_match=first)  # a writer that read the first version
    assert objects.read_bytes(where) == b"three"


def second_writer_cannot_publish(root: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Writer B publishes a folder while writer A (another batch on the same folder) uploads there: A's
    conditional create of the manifest is refused with one line, and the folder stays B's, whole."""
    target = location(f"{root}/race/scan")
    theirs, ours = tmp_path / "b", tmp_path / "a"
    for folder, text in ((theirs, "b"), (ours, "a")):
        folder.mkdir()
        (folder / "data.txt").write_text(text)
        (folder / MANIFEST_FILE).write_text(json.dumps({"files": {"data.txt": text}}))
    upload = objects.upload_files

    def upload_while_b_publishes(local_dir: Path, where, skip=()):  # B publishes between A's upload and manifest
        names = upload(local_dir, where, skip)
        objects.write_object(where.joinpath(MANIFEST_FILE), (theirs / MANIFEST_FILE).read_bytes(), create=True)
        return names

    monkeypatch.setattr(objects, "upload_files", upload_while_b_publishes)
    with pytest.raises(MpiLidarError) as error:
        objects.publish_directory(ours, target)
    assert "\n" not in str(error.value) and "published by another writer" in str(error.value)
    assert objects.read_bytes(target.joinpath(MANIFEST_FILE)) == (theirs / MANIFEST_FILE).read_bytes()


def stale_lock_taken_over_once(root: str) -> None:
    """A lock whose holder stopped renewing it is taken over by a conditional overwrite of the version read:
    of two batches taking it over from that version only the first succeeds; a lock held and renewed refuses a
    second batch with one line; released, the next batch takes it."""
    out = location(f"{root}/locked")
    lock = out.joinpath(LOCK_FILE)
    dead = {"holder": "pid 1 on gone-host, started long ago", "pid": 1, "host": "gone-host", "renewed": 0.0}
    objects.write_object(lock, json.dumps(dead).encode(), create=True)
    read = objects._conditional.version(lock.scheme, objects.filesystem(lock).info(lock.path))
    with objects.ObjectOutputLock(out).hold():
        held = json.loads(objects.read_bytes(lock) or b"{}")
        assert held["pid"] == os.getpid()  # taken over from the dead holder
        with pytest.raises(FileExistsError):  # a second batch that read the same stale version
            objects.write_object(lock, json.dumps(dead).encode(), if_match=read)
        refused: list[str] = []
        second = threading.Thread(target=_hold_into, args=(out, refused))
        second.start()
        second.join()
        assert len(refused) == 1 and "\n" not in refused[0] and "being written by another" in refused[0]
    assert objects.read_bytes(lock) is None  # released
    refused.clear()
    _hold_into(out, refused)
    assert refused == []


def lock_renewed_while_held(root: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The holder renews its lock by conditional overwrites of the version each renewal returned (the store's
    own token: an ETag, a generation), so a lock held stays fresh; a renewal that failed would leave it to go
    stale and be taken over mid-batch."""
    monkeypatch.setattr(objects, "_RENEW_EVERY_S", 0.05)
    out = location(f"{root}/renewed")
    lock = out.joinpath(LOCK_FILE)
    with objects.ObjectOutputLock(out).hold():
        first = json.loads(objects.read_bytes(lock) or b"{}")["renewed"]
        deadline = time.monotonic() + 5
        while json.loads(objects.read_bytes(lock) or b"{}")["renewed"] == first and time.monotonic() < deadline:
            time.sleep(0.05)
        renewed = json.loads(objects.read_bytes(lock) or b"{}")["renewed"]
        time.sleep(0.3)  # several renewals more, each over the version the one before wrote
        last = json.loads(objects.read_bytes(lock) or b"{}")["renewed"]
    assert first < renewed < last


def _hold_into(out, refused: list[str]) -> None:
    try:
        with objects.ObjectOutputLock(out).hold():
            pass
    except MpiLidarError as exc:
        refused.append(str(exc))


def archive_in(root: str, tmp_path: Path, count: int = 3, prefix: str = "scans") -> tuple[Path, str]:
    """``count`` scans of 24 x 32 on the local disk and the same below ``<root>/<prefix>``: (folder, URL)."""
    local = tmp_path / prefix
    for k in range(count):
        write_scan(two_path_scan(f"scan{k}", seed=k), local / f"scan{k}.scan.zarr")
    url = f"{root}/{prefix}"
    objects.filesystem(location(url)).put(str(local) + "/", location(url).path, recursive=True)
    return local, url


def corrected_outputs_match_local(root: str, model: Path, tmp_path: Path, monkeypatch, capsys, caplog,
                                  secret: str | None) -> None:
    """Scans corrected from and into the store: outputs bit-identical to a local run's but for provenance and
    times, every scan's folder and store verified, a re-run skipping all, and ``secret`` (the credential the
    store was reached with, where it takes one) nowhere."""
    local, url = archive_in(root, tmp_path, count=2)  # a batch of more than one scan
    out = f"{root}/out"
    code, _, err = call_main(monkeypatch, capsys, "correct", str(local), "--model", model, "--out", tmp_path / "here")
    assert code == 0, err
    code, stdout, err = call_main(monkeypatch, capsys, "correct", url + "/", "--model", model, "--out", out)
    assert code == 0, err
    assert f"summary: {out}/summary/report.html" in stdout
    there = tmp_path / "there"
    objects.filesystem(location(out)).get(location(out).path + "/", str(there), recursive=True)
    here, got = files_of(tmp_path / "here"), files_of(there)
    assert sorted(got) == sorted(n for n in here if not n.startswith(".mpi-lidar-correct.lock"))
    differing = sorted(n for n in here if n in got and got[n] != here[n])
    assert all(n.startswith("summary/") or n.split("/", 1)[1] in PROVENANCE for n in differing), differing
    for name in (n for n in differing if not n.startswith("summary/")):
        if name.endswith((".json", MANIFEST_FILE)):
            assert untimed(json.loads(got[name])) == untimed(json.loads(here[name])), name
        else:
            assert TIMES.sub(b"", got[name]) == TIMES.sub(b"", here[name]), name
    assert any("corrected.zarr/corrected_depth/c/" in n for n in got)  # chunks bit-identical, not only listed
    folders = [f"{out}/scan{k}" for k in range(2)]
    code, stdout, err = call_main(monkeypatch, capsys, "verify", *folders, *(f"{f}/corrected.zarr" for f in folders))
    assert code == 0 and stdout.count("ok ") == 4, stdout + err
    code, stdout, err = call_main(monkeypatch, capsys, "correct", url, "--model", model, "--out", out)
    assert code == 0 and "2 already done" in stdout, stdout + err
    blob = b"".join(got.values()).decode(errors="replace") + stdout + err + caplog.text
    assert secret is None or secret not in blob


def killed_writer_leaves_no_output(root: str, model: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    """A batch killed (kill -9) once its first scan is published: every scan then is published whole or not
    there for any reader (the skip, ``verify``); the re-run (a process of its own, like the user's next command)
    publishes the rest, and none twice."""
    _, url = archive_in(root, tmp_path, count=4, prefix="killed-scans")
    out = f"{root}/killed"
    fs = objects.filesystem(location(out))
    command = [sys.executable, "-c", "from mpi_lidar.cli import main; main()", "correct", url, "--model", str(model),
               "--out", out, "--outputs", "data"]
    batch = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    pattern = f"{location(out).path}/scan*/{MANIFEST_FILE}"
    deadline = time.monotonic() + 60
    while not fs.glob(pattern) and time.monotonic() < deadline and batch.poll() is None:
        time.sleep(0.1)  # a scan takes longer: the batch is killed with the others still to publish
    batch.send_signal(signal.SIGKILL)
    batch.communicate()
    published = {p.split("/")[-2] for p in fs.glob(pattern)}
    assert 1 <= len(published) < 4, published
    for k in range(4):
        folder = location(f"{out}/scan{k}")
        if folder.name in published:
            assert objects.published_damage(folder) is None
            objects.verify_published(folder)
        else:
            assert objects.published_damage(folder) is not None
            code, _, err = call_main(monkeypatch, capsys, "verify", f"{folder}/corrected.zarr")
            assert code == 1 and "not published" in err, err
    versions = _manifest_versions(out, published)
    rerun = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert rerun.returncode == 0 and f"{len(published)} already done" in rerun.stdout, rerun.stdout + rerun.stderr
    assert rerun.stderr == ""  # nothing at exit either (the store libraries' sessions closed quietly)
    assert _manifest_versions(out, published) == versions  # published once, never again
    assert len(fs.glob(pattern)) == 4


def dataset_and_model_published(root: str, tmp_path: Path, monkeypatch, capsys) -> None:
    """``simulate`` writes a dataset into the store (its chunks through zarr), bit-identical to one on disk and
    complete for a second run; ``train`` reads it there and publishes a model there, never over one."""
    from mpi_lidar.simulation import dataset
    from mpi_lidar.workflows.generate import generate

    (tmp_path / "small.toml").write_text("[dataset]\nsamples = 600\nchunk_rows = 300\nseed = 3\n")
    (tmp_path / "params.json").write_text('{"max_depth": 2, "learning_rate": 0.9}')
    url, model = f"{root}/datasets/d.zarr", f"{root}/models/m"
    simulate = ("simulate", "--out", url, "--config", tmp_path / "small.toml", "--workers", "0")
    code, stdout, err = call_main(monkeypatch, capsys, *simulate)
    assert code == 0 and f"dataset {url}: 600 rows" in stdout, stdout + err
    assert "0 of 2 chunks simulated" in call_main(monkeypatch, capsys, *simulate)[1]
    generate(tmp_path / "d.zarr", dataset.store_config(dataset.open_store(url)))
    there, here = dataset.read_verified(url), dataset.read_verified(tmp_path / "d.zarr")
    assert all(np.array_equal(there[name], here[name]) for name in dataset.DATA_ARRAYS)
    train = ("train", "--data", url, "--out", model, "--params", tmp_path / "params.json", "--workers", "0")
    code, stdout, err = call_main(monkeypatch, capsys, *train)
    assert code == 0 and f"model written to {model}" in stdout, stdout + err
    code, _, err = call_main(monkeypatch, capsys, *train)
    assert code == 2 and f"model directory {model} already exists" in err, err


def _manifest_versions(out: str, folders: set[str]) -> dict[str, str]:
    """The version (ETag or generation) of each folder's manifest below ``out``."""
    where = location(out)
    fs = objects.filesystem(where)
    return {name: objects._conditional.version(where.scheme, fs.info(f"{where.path}/{name}/{MANIFEST_FILE}"))
            for name in folders}


# --- the cases on Azure -----------------------------------------------------------------------------------------


@pytest.mark.integration
def test_write_object__conditional_create_and_overwrite_on_azure(azure_root):
    conditional_writes_are_atomic(azure_root)


@pytest.mark.integration
def test_publish_directory__second_writer_refused_on_azure(azure_root, tmp_path, monkeypatch):
    second_writer_cannot_publish(azure_root, tmp_path, monkeypatch)


@pytest.mark.integration
def test_object_output_lock__stale_lock_taken_over_once_on_azure(azure_root):
    stale_lock_taken_over_once(azure_root)


@pytest.mark.integration
def test_object_output_lock__renewed_while_held_on_azure(azure_root, monkeypatch):
    lock_renewed_while_held(azure_root, monkeypatch)


@pytest.mark.integration
@pytest.mark.slow
def test_correct__container_outputs_identical_to_local_and_verified(azure_root, pixelwise_model, tmp_path,
                                                                   monkeypatch, capsys, caplog):
    corrected_outputs_match_local(azure_root, pixelwise_model, tmp_path, monkeypatch, capsys, caplog, ACCOUNT_KEY)


@pytest.mark.integration
@pytest.mark.slow
def test_simulate_and_train__dataset_and_model_in_container(azure_root, tmp_path, monkeypatch, capsys):
    dataset_and_model_published(azure_root, tmp_path, monkeypatch, capsys)


@pytest.mark.integration
@pytest.mark.slow
def test_correct__killed_batch_on_azure_leaves_only_whole_outputs(azure_root, pixelwise_model, tmp_path,
                                                                  monkeypatch, capsys):
    killed_writer_leaves_no_output(azure_root, pixelwise_model, tmp_path, monkeypatch, capsys)
