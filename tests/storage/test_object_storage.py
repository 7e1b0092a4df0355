"""Scans read from and outputs published to a real S3-compatible server (moto's, started here on 127.0.0.1)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mpi_lidar import cli
from mpi_lidar.locations import location
from mpi_lidar.scans.store import read_scan, write_scan
from mpi_lidar.storage import objects
from mpi_lidar.storage.manifest import MANIFEST_FILE
from mpi_lidar.workflows.archive_paths import expand_archive
from tests.cli_runner import call_main
from tests.scan_factory import two_path_scan
from tests.storage.conftest import BUCKET, SECRET, versioned_bucket, versions_written

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
# Outputs that name where they came from and when: the only bytes allowed to differ from a local run.
PROVENANCE = ("report.md", "report.html", "metrics.json", MANIFEST_FILE, "corrected.zarr/zarr.json")
TIMES = re.compile(rb"[0-9.]+ s\b|[0-9]+\.[0-9]+ (?:s|scans/s)")


def untimed(data: object) -> object:
    """JSON without what differs between two runs: seconds taken, and the digests and sizes of the files that
    hold them (the manifest's entries of metrics.json and the reports)."""
    if isinstance(data, dict):
        if "total" in data and all(isinstance(v, float) for v in data.values()):
            return "timings"
        return {k: untimed(v) for k, v in data.items()
                if not (k.endswith(("metrics.json", "report.md", "report.html")) or "second" in k or k.endswith("_s"))}
    if isinstance(data, list):
        return [untimed(v) for v in data]
    return data


@pytest.fixture(scope="module")
def archive(s3_server, tmp_path_factory) -> tuple[Path, str]:
    """Three scans of 24 x 32 on the local disk, and the same in the bucket: (local folder, URL)."""
    local = tmp_path_factory.mktemp("archive") / "scans"
    for k in range(3):
        write_scan(two_path_scan(f"scan{k}", seed=k), local / f"scan{k}.scan.zarr")
    url = f"s3://{BUCKET}/scans"
    objects.filesystem(location(url)).put(str(local) + "/", f"{BUCKET}/scans", recursive=True)
    return local, url


@pytest.fixture(scope="module")
def corrected_here(archive, pixelwise_model, tmp_path_factory) -> Path:
    """The archive's scans corrected on the local disk by the command line, at its default output level: what
    the bucket's outputs are compared with."""
    out = tmp_path_factory.mktemp("here") / "out"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sys, "argv", ["mpi-lidar", "correct", str(archive[0]), "--model", str(pixelwise_model),
                                    "--out", str(out)])
        try:
            cli.main()
        except SystemExit as exc:
            assert not exc.code, exc.code
    return out


def download(url: str, into: Path) -> Path:
    objects.filesystem(location(url)).get(location(url).path + "/", str(into), recursive=True)
    return into


def files_of(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_read_scan__from_bucket_equals_local(archive):
    local, url = archive
    assert expand_archive([url + "/"]) == [f"{url}/scan{k}.scan.zarr" for k in range(3)]
    assert expand_archive([url + "/scan[02].scan.zarr"]) == [f"{url}/scan0.scan.zarr", f"{url}/scan2.scan.zarr"]
    there, here = read_scan(f"{url}/scan1.scan.zarr"), read_scan(local / "scan1.scan.zarr")
    assert there.content_sha256() == here.content_sha256() and there.name == "scan1"


def test_read_scan__damaged_chunk_in_bucket_refused(archive, tmp_path):
    from mpi_lidar.storage.integrity import IntegrityError

    local, _ = archive
    url = f"s3://{BUCKET}/damaged/scan0.scan.zarr"
    fs = objects.filesystem(location(url))
    fs.put(str(local / "scan0.scan.zarr") + "/", location(url).path, recursive=True)
    fs.pipe_file(f"{location(url).path}/depth/c/1/0/0", (local / "scan0.scan.zarr/depth/c/0/0/0").read_bytes())
    with pytest.raises(IntegrityError, match=r"chunk .1, 0, 0. of 'depth'"):
        read_scan(url)


@pytest.mark.slow
def test_correct__bucket_outputs_identical_to_local_and_verified(archive, corrected_here, pixelwise_model, tmp_path,
                                                                 monkeypatch, capsys, caplog):
    _, url = archive
    out = f"s3://{BUCKET}/out"
    code, stdout, err = call_main(monkeypatch, capsys, "correct", url + "/", "--model", pixelwise_model, "--out", out)
    assert code == 0, err
    assert f"summary: {out}/summary/report.html" in stdout
    there = download(out, tmp_path / "bucket")
    here = files_of(corrected_here)
    got = files_of(there)
    assert sorted(got) == sorted(n for n in here if not n.startswith(".mpi-lidar-correct.lock"))
    differing = sorted(n for n in here if n in got and got[n] != here[n])
    assert all(n.startswith("summary/") or n.split("/", 1)[1] in PROVENANCE for n in differing), differing
    # The summary names each scan's source (a path or a URL); its links to the reports are the same.
    assert b'href="../scan0/report.html"' in got["summary/report.html"]
    for name in (n for n in differing if not n.startswith("summary/")):  # the seconds taken and their digests
        if name.endswith(".json") or name.endswith(MANIFEST_FILE):
            assert untimed(json.loads(got[name])) == untimed(json.loads(here[name])), name
        else:
            assert TIMES.sub(b"", got[name]) == TIMES.sub(b"", here[name]), name
    assert any("corrected.zarr/corrected_depth/c/" in n for n in got)  # the chunks themselves are bit-identical
    for k in range(3):
        code, stdout, err = call_main(monkeypatch, capsys, "verify", f"{out}/scan{k}", f"{out}/scan{k}/corrected.zarr")
        assert code == 0 and stdout.count("ok ") == 2, err
    # A re-run skips every scan: their published manifests verify.
    code, stdout, err = call_main(monkeypatch, capsys, "correct", url, "--model", pixelwise_model, "--out", out)
    assert code == 0 and "3 already done" in stdout, stdout + err
    # No credential anywhere: outputs, terminal, log records.
    blob = b"".join(got.values()).decode(errors="replace") + stdout + err + caplog.text
    assert SECRET not in blob and "S3cr3t" not in blob


@pytest.mark.slow
def test_verify__unpublished_or_edited_output_in_bucket_fails(archive, pixelwise_model, tmp_path, monkeypatch,
                                                              capsys):
    _, url = archive
    out = f"s3://{BUCKET}/tampered"
    batch = ("correct", f"{url}/scan0.scan.zarr", f"{url}/scan1.scan.zarr", "--model", pixelwise_model, "--out", out,
             "--outputs", "data")  # the store and metrics.json: what verify checks
    code, _, err = call_main(monkeypatch, capsys, *batch)
    assert code == 0, err
    fs = objects.filesystem(location(out))
    fs.pipe_file(f"{BUCKET}/tampered/scan0/metrics.json", b"{}\n")
    fs.rm_file(f"{BUCKET}/tampered/scan1/{MANIFEST_FILE}")
    code, _, err = call_main(monkeypatch, capsys, "verify", f"{out}/scan0")
    assert code == 1 and "metrics.json" in err, err
    code, _, err = call_main(monkeypatch, capsys, "verify", f"{out}/scan1/corrected.zarr")
    assert code == 1 and "not published" in err, err
    # The re-run corrects both again and publishes each once more.
    code, stdout, err = call_main(monkeypatch, capsys, *batch)
    assert code == 0 and "already done" not in stdout, stdout + err
    assert call_main(monkeypatch, capsys, "verify", f"{out}/scan0", f"{out}/scan1")[0] == 0


def test_publish_directory__second_writer_cannot_publish(s3_server, tmp_path):
    folder = tmp_path / "outputs"
    folder.mkdir()
    (folder / "a.txt").write_text("a")
    (folder / MANIFEST_FILE).write_text("{}")
    target = location(f"s3://{BUCKET}/race/scan")
    objects.upload_files(folder, target)  # a writer that published meanwhile: its manifest is there
    with pytest.raises(FileExistsError):
        objects.write_object(target.joinpath(MANIFEST_FILE), b"{}", create=True)


@pytest.mark.slow
def test_correct__killed_dask_worker_resumes_publishing_each_scan_once(archive, corrected_here, pixelwise_model,
                                                                       tmp_path):
    """Two Dask workers read the scans from and publish to a bucket that keeps every version of every object;
    one is killed (kill -9) while it corrects a scan. The scheduler runs its scans again on the other: every
    scan is published exactly once (one version of each manifest), verifies, and its chunks are those of the
    scans corrected in this process."""
    from mpi_lidar.workflows.cluster import dask_client
    from mpi_lidar.workflows.correct_archive import correct_archive
    from mpi_lidar.workflows.verify import verify_store

    local, _ = archive
    bucket = versioned_bucket("killed-worker")
    fs = objects.filesystem(location(f"s3://{bucket}"))
    fs.put(str(local) + "/", f"{bucket}/scans", recursive=True)
    # A fourth scan: once the first is published, three are left for the two workers.
    write_scan(two_path_scan("scan3", seed=3), tmp_path / "more" / "scan3.scan.zarr")
    fs.put(str(tmp_path / "more") + "/", f"{bucket}/scans", recursive=True)
    out = f"s3://{bucket}/out"
    with dask_client(None, 2) as client:
        pids = client.run(os.getpid)
        killed: dict[str, int] = {}

        def kill_once_one_is_published(outcome) -> None:  # a scan's task ends once its outputs are published
            if not killed:
                _kill_a_busy_worker(client, pids, fs, f"{bucket}/out", killed)

        outcomes = correct_archive([f"s3://{bucket}/scans"], pixelwise_model, out, client=client, outputs="data",
                                   on_scan=kill_once_one_is_published)
    assert killed and 1 <= killed["published"] < 4, killed  # killed mid-batch, while correcting a scan
    assert [o.status.value for o in outcomes if o.status.value == "failed"] == [], [o.reason for o in outcomes]
    for k in range(4):
        assert versions_written(bucket, f"out/scan{k}/{MANIFEST_FILE}") == 1, k
        verify_store(f"{out}/scan{k}")  # the manifest's every object, and the store's every chunk
    here = files_of(corrected_here)  # the chunks are the same at every output level
    there = files_of(download(out, tmp_path / "there"))
    chunks = {n for n in here if "/c/" in n}
    assert chunks and {n: here[n] for n in chunks} == {n: there[n] for n in chunks}


def _kill_a_busy_worker(client, pids: dict[str, int], fs, out_key: str, killed: dict[str, int]) -> None:
    """kill -9 a worker that is correcting a scan; what it did, in ``killed`` (how many scans were published
    then)."""
    busy = [address for address, keys in client.processing().items() if keys and address in pids]
    if busy:
        killed.update(published=len(fs.glob(f"{out_key}/scan*/{MANIFEST_FILE}")), pid=pids[busy[0]])
        os.kill(pids[busy[0]], signal.SIGKILL)


@pytest.mark.slow
def test_correct__killed_batch_resumes_publishing_each_scan_once(s3_server, pixelwise_model, tmp_path):
    local = tmp_path / "scans"
    for k in range(4):
        write_scan(two_path_scan(f"frame{k}", seed=10 + k), local / f"frame{k}.scan.zarr")
    fs = objects.filesystem(location(f"s3://{BUCKET}"))
    fs.put(str(local) + "/", f"{BUCKET}/killed-scans", recursive=True)
    out = f"s3://{BUCKET}/killed"
    command = [sys.executable, "-c", "from mpi_lidar.cli import main; main()", "correct",
               f"s3://{BUCKET}/killed-scans", "--model", str(pixelwise_model), "--out", out, "--outputs", "data"]
    batch = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    manifests: list[str] = []
    deadline = time.monotonic() + 120
    while not manifests and time.monotonic() < deadline and batch.poll() is None:
        manifests = fs.glob(f"{BUCKET}/killed/frame*/{MANIFEST_FILE}")
        time.sleep(0.1)  # a scan takes longer: the batch is killed with the others still to publish
    batch.send_signal(signal.SIGKILL)
    stdout, stderr = batch.communicate()
    published = set(fs.glob(f"{BUCKET}/killed/frame*/{MANIFEST_FILE}"))
    assert 1 <= len(published) < 4, (published, stderr)
    # What a reader sees now: every published scan whole, every other one not there.
    for k in range(4):
        folder = f"{out}/frame{k}"
        if f"{BUCKET}/killed/frame{k}/{MANIFEST_FILE}" in published:
            assert objects.published_damage(location(folder)) is None
            objects.verify_published(location(folder))
        else:
            assert objects.published_damage(location(folder)) is not None
    etags = {path: fs.info(path)["ETag"] for path in published}
    rerun = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert f"{len(published)} already done" in rerun.stdout, rerun.stdout
    assert {path: fs.info(path)["ETag"] for path in published} == etags  # published once, never again
    assert len(fs.glob(f"{BUCKET}/killed/frame*/{MANIFEST_FILE}")) == 4
    text = stdout + stderr + rerun.stdout + rerun.stderr
    assert SECRET not in text and "S3cr3t" not in text
