"""Two batches into one output directory at once: the second is refused with one line naming the first, and
the first's outputs and summary are whole. Tested with real processes."""

from __future__ import annotations

import fcntl
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.scans.store import write_scan
from mpi_lidar.storage.publication import LOCK_FILE, output_lock
from mpi_lidar.workflows.correct_archive import correct_archive
from mpi_lidar.workflows.verify import verify_store
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[2]

# A batch (as the command line runs it: correct_archive, then the summary) that stops after its first scan
# until told to go on, so that a second batch can be started while it holds the output directory.
FIRST_BATCH = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from mpi_lidar.correction import CorrectionOptions
    from mpi_lidar.reporting.batch_report import write_batch_report
    from mpi_lidar.workflows.correct_archive import correct_archive

    scans, model, out, ready, go = sys.argv[1:]

    def on_scan(outcome):
        Path(ready).write_text("holding")
        deadline = time.monotonic() + 300
        while not Path(go).exists() and time.monotonic() < deadline:
            time.sleep(0.05)

    outcomes = correct_archive([scans], model, out, CorrectionOptions(gate="all"), on_scan=on_scan, outputs="data")
    write_batch_report(outcomes, 1.0, out)
    print(" ".join(str(o.status) for o in outcomes))
""")


def run_cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", "from mpi_lidar.cli import main; main()", *map(str, args)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    return tiny_model(tmp_path_factory.mktemp("model") / "model")


def test_two_batches_into_one_out__the_second_is_refused_naming_the_first(model, tmp_path):
    for seed, name in enumerate(("a", "b")):
        write_scan(two_path_scan(name, seed=seed), tmp_path / "scans" / f"{name}.scan.zarr")
    out, ready, go = tmp_path / "out", tmp_path / "ready", tmp_path / "go"
    first = subprocess.Popen([sys.executable, "-c", FIRST_BATCH, str(tmp_path / "scans"), str(model), str(out),
                              str(ready), str(go)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while not ready.exists() and first.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert ready.exists(), first.communicate()[1]
        second = run_cli("correct", tmp_path / "scans", "--model", model, "--out", out, "--gate", "all",
                         "--outputs", "data")
        assert second.returncode == 2, second.stderr
        [line] = second.stderr.strip().splitlines()
        assert line.startswith("error: output directory") and "being written by another correct run" in line
        assert f"pid {first.pid} on " in line, "the error names the run that holds the output"
        assert not (out / "summary").exists(), "the refused batch wrote nothing"
    finally:
        go.write_text("go")
        stdout, stderr = first.communicate(timeout=300)
    assert first.returncode == 0, stderr
    assert stdout.split() == ["corrected", "corrected"]
    summary = (out / "summary" / "report.md").read_text()
    assert "| a |" in summary and "| b |" in summary, "the summary is the first batch's, whole"
    assert not (out / LOCK_FILE).exists(), "the lock goes with its batch"
    again = run_cli("correct", tmp_path / "scans", "--model", model, "--out", out, "--gate", "all", "--outputs", "data")
    assert again.returncode == 0, again.stderr
    assert "2 already done" in again.stdout
    for name in ("a", "b"):
        assert verify_store(out / name).files > 0


def test_output_lock__held_by_another_process_is_refused_with_its_holder(tmp_path):
    holder = subprocess.Popen([sys.executable, "-c", textwrap.dedent("""
        import sys, time
        from mpi_lidar.storage.publication import output_lock
        with output_lock(sys.argv[1]):
            print("held", flush=True)
            sys.stdin.readline()
    """), str(tmp_path)], cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with pytest.raises(MpiLidarError, match=rf"being written by another correct run \(pid {holder.pid} on "):
            with output_lock(tmp_path):
                pass
    finally:
        holder.communicate("\n", timeout=60)
    with output_lock(tmp_path):  # free again once its holder is done
        assert (tmp_path / LOCK_FILE).exists()
    assert not (tmp_path / LOCK_FILE).exists()


def test_output_lock__a_file_left_by_a_killed_run_does_not_block(tmp_path):
    (tmp_path / LOCK_FILE).write_text("pid 1 on elsewhere, started long ago\n")  # its flock died with it
    with output_lock(tmp_path):
        assert f"pid {os.getpid()} on " in (tmp_path / LOCK_FILE).read_text()
    assert not (tmp_path / LOCK_FILE).exists()


def test_output_lock__nested_holds_in_one_process_are_one(tmp_path):
    with output_lock(tmp_path):
        with output_lock(tmp_path / "."):
            assert (tmp_path / LOCK_FILE).exists()
        assert (tmp_path / LOCK_FILE).exists(), "the outer hold still holds it"
        with open(tmp_path / LOCK_FILE) as file:  # another open file description: the lock is really taken
            with pytest.raises(BlockingIOError):
                fcntl.flock(file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    assert not (tmp_path / LOCK_FILE).exists()


def test_correct_archive__holds_its_output_while_it_runs(model, tmp_path):
    write_scan(two_path_scan("a"), tmp_path / "a.scan.zarr")
    seen: list[bool] = []

    def on_scan(outcome) -> None:
        with open(tmp_path / "out" / LOCK_FILE) as file:
            try:
                fcntl.flock(file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                seen.append(False)
            except BlockingIOError:
                seen.append(True)

    correct_archive([str(tmp_path / "a.scan.zarr")], model, tmp_path / "out", CorrectionOptions(gate="all"),
                    on_scan=on_scan, outputs="data")
    assert seen == [True] and not (tmp_path / "out" / LOCK_FILE).exists()


def test_output_lock__another_thread_of_the_same_process_is_refused(tmp_path):
    import threading

    refused: list[str] = []

    def second() -> None:
        try:
            with output_lock(tmp_path):
                pass
        except MpiLidarError as exc:
            refused.append(str(exc))

    with output_lock(tmp_path):
        thread = threading.Thread(target=second)
        thread.start()
        thread.join()
    assert len(refused) == 1 and f"pid {os.getpid()} on " in refused[0]
