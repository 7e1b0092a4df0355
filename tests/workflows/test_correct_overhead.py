"""Per-scan overhead of batch correction: light imports, a batch in this process, one model load."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from mpi_lidar.cli import cli
from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.reporting.output_levels import DEFAULT_OUTPUTS, OUTPUT_LEVELS
from mpi_lidar.scans.store import write_scan
from mpi_lidar.workflows import correct_archive as archive_module
from mpi_lidar.workflows.correct_archive import correct_archive
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

HEAVY = ("dask", "distributed", "xgboost", "zarr", "matplotlib", "scipy", "optuna", "pandas")


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("archive")
    for index in range(3):
        write_scan(two_path_scan(f"s{index}", seed=index), root / f"s{index}.scan.zarr")
    return root


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    return tiny_model(tmp_path_factory.mktemp("model") / "model", geometric=False, feature_set="raw")


def _imported_after(statement: str) -> set[str]:
    code = f"import sys; {statement}; print(' '.join(sorted({{m.split('.')[0] for m in sys.modules}})))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                          env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])})
    return set(done.stdout.split())


@pytest.mark.integration
def test_cli__help_imports_no_numerics_library():
    assert not _imported_after("import mpi_lidar.cli") & set(HEAVY)


@pytest.mark.unit
def test_executor__a_loop_in_this_process_needs_no_dask():
    assert "distributed" not in _imported_after("from mpi_lidar.workflows.executor import InProcess, as_executor; "
                                                "as_executor(None)")


@pytest.mark.integration
def test_correct_cli__outputs_choices_are_the_levels_and_light_is_the_default():
    option = next(p for p in cli.commands["correct"].params if p.name == "outputs")
    assert tuple(option.type.choices) == OUTPUT_LEVELS and option.default == DEFAULT_OUTPUTS == "light"


@pytest.mark.integration
def test_correct_cli__every_batch_runs_here_unless_workers_are_asked_for(archive, model_dir, tmp_path, monkeypatch):
    from mpi_lidar.workflows import executor

    started: list[int] = []

    def no_cluster(scheduler=None, workers=2):
        started.append(workers)
        raise RuntimeError("no cluster in this test")

    monkeypatch.setattr(executor, "dask_executor", no_cluster)
    arguments = ["correct", str(archive), "--model", str(model_dir), "--gate", "all"]
    assert CliRunner().invoke(cli, [*arguments, "--out", str(tmp_path / "a")]).exit_code == 0
    assert started == [] and (tmp_path / "a" / "s0" / "thumbnail.png").exists()
    assert CliRunner().invoke(cli, [*arguments, "--out", str(tmp_path / "z"), "--workers", "0"]).exit_code == 0
    assert started == [] and (tmp_path / "z" / "s2" / "thumbnail.png").exists()
    result = CliRunner().invoke(cli, [*arguments, "--out", str(tmp_path / "b"), "--workers", "3"])
    assert started == [3] and isinstance(result.exception, RuntimeError)


@pytest.mark.unit
def test_cached_model__loaded_once_per_process_and_again_when_replaced(archive, model_dir, tmp_path, monkeypatch):
    loads: list[str] = []
    real = archive_module.load_model
    monkeypatch.setattr(archive_module, "load_model", lambda path: loads.append(str(path)) or real(path))
    archive_module._load_model.cache_clear()
    outcomes = correct_archive([str(archive)], model_dir, tmp_path / "out", CorrectionOptions(gate="all"),
                               outputs="data")
    assert [o.status for o in outcomes] == ["corrected"] * 3 and loads == [str(model_dir)]
    card = model_dir / "card.json"
    os.utime(card, ns=(card.stat().st_atime_ns, card.stat().st_mtime_ns + 1_000_000))
    correct_archive([str(archive)], model_dir, tmp_path / "again", CorrectionOptions(gate="all"), outputs="data")
    assert loads == [str(model_dir)] * 2, "a model whose files changed is loaded again"


HEAP_PROBE = """
import ctypes, os, re, sys, tempfile, threading
import numpy as np
from mpi_lidar.workflows.correct_archive import share_one_heap

libc = ctypes.CDLL(None)
libc.fopen.restype = ctypes.c_void_p

def heaps():
    handle, path = tempfile.mkstemp()
    os.close(handle)
    report = libc.fopen(path.encode(), b"w")
    libc.malloc_info(0, ctypes.c_void_p(report))
    libc.fclose(ctypes.c_void_p(report))
    found = len(re.findall('<heap nr=', open(path).read()))
    os.unlink(path)
    return found

def allocate_in_a_thread():
    arrays = [np.ones(2_000) for _ in range(50)]  # 16 kB each: from a heap, not a mapping of their own
    del arrays

if sys.argv[1] == "shared":
    assert share_one_heap()
before = heaps()
thread = threading.Thread(target=allocate_in_a_thread)
thread.start()
thread.join()
print(heaps() - before)
"""


def _heaps_a_thread_adds(*modes: str) -> list[int]:
    """Per mode, the heaps a thread adds in a fresh process of its own; the processes run side by side."""
    probes = [subprocess.Popen([sys.executable, "-c", HEAP_PROBE, mode], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, cwd=Path(__file__).parents[2]) for mode in modes]
    found = []
    for probe in probes:
        stdout, stderr = probe.communicate(timeout=300)
        assert probe.returncode == 0, stderr
        found.append(int(stdout.strip()))
    return found


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_archive_scans__every_thread_allocates_from_one_heap():
    default, shared = _heaps_a_thread_adds("default", "shared")
    assert default == 1  # glibc: a new thread gets a heap of its own ...
    assert shared == 0  # ... which archive correction does away with
