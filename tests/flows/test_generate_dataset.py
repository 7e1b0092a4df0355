"""The generation flow on a 2-worker LocalCluster: same bytes as the library, files, artifact and task runs."""

from __future__ import annotations

from pathlib import Path

import pytest
import zarr
from matplotlib import pyplot as plt

from flows import generate_dataset
from flows.generate_dataset import SUMMARY_ARTIFACT_KEY, generate_dataset_flow, histogram_path
from mpi_lidar.config import config_sha256, resolve_config
from mpi_lidar.simulation import dataset
from mpi_lidar.workflows.generate import generate
from tests.flows.helpers import CHUNKS, SAMPLES, artifacts, chunk_task_runs, wait_for

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory, config_file: Path) -> dict[str, object]:
    """One flow run on its own 2-process LocalCluster, shared by the tests of this module."""
    out = tmp_path_factory.mktemp("generated") / "dataset.zarr"
    return generate_dataset_flow(out=str(out), config_file=str(config_file), workers=2)


@pytest.mark.slow
def test_generate_dataset_flow__store_equals_in_process_generation(
    generated: dict[str, object], config_file: Path, tmp_path: Path
) -> None:
    config = resolve_config(config_file, "quick")
    reference = tmp_path / "reference.zarr"
    generate(reference, config)
    flow_store, library_store = zarr.open_group(generated["path"], mode="r"), zarr.open_group(reference, mode="r")
    for name in ("features", "target", "theta", "split"):
        ours, theirs = flow_store[name][:], library_store[name][:]
        assert ours.dtype == theirs.dtype and ours.shape == theirs.shape, name
        assert ours.tobytes() == theirs.tobytes(), f"{name} differs from the in-process store"
    assert dataset.dataset_info(generated["path"]).complete


def test_generate_dataset_flow__result_counts_chunks_and_rows(generated: dict[str, object], config_file: Path) -> None:
    assert generated["chunks_written"] == CHUNKS
    assert generated["chunks_skipped"] == 0
    assert generated["rows_written"] == SAMPLES
    assert generated["wall_s"] > 0 and generated["rows_per_s"] == pytest.approx(SAMPLES / generated["wall_s"])
    assert generated["config_sha256"] == config_sha256(resolve_config(config_file, "quick"))


def test_generate_dataset_flow__writes_error_histogram_png_beside_store(generated: dict[str, object]) -> None:
    png = Path(generated["png"])
    assert png == Path(generated["path"]).with_name("dataset.error_hist.png")
    assert png.read_bytes()[:8] == PNG_SIGNATURE
    height, width, _ = plt.imread(png).shape
    assert height > 100 and width > 100


def test_generate_dataset_flow__publishes_markdown_summary_artifact(generated: dict[str, object]) -> None:
    found = artifacts(generated["flow_run_id"], SUMMARY_ARTIFACT_KEY)
    assert len(found) == 1
    markdown = found[0].data
    assert found[0].type == "markdown"
    assert "| 31.25 MHz |" in markdown and "noise-only MAE" in markdown
    assert f"| wall time | {generated['wall_s']:.2f} s |" in markdown
    assert "| throughput |" in markdown and f"| rows written | {SAMPLES:,} |" in markdown
    assert "LocalCluster, 2 processes" in markdown


def test_generate_dataset_flow__records_one_completed_task_run_per_chunk(generated: dict[str, object]) -> None:
    expected = {f"write-chunk-{i}" for i in range(CHUNKS)}

    def ready(runs: list) -> bool:
        return {r.name for r in runs if r.state_type and r.state_type.value == "COMPLETED"} == expected

    runs = wait_for(lambda: chunk_task_runs(generated["flow_run_id"]), ready)
    assert sorted(r.name for r in runs) == sorted(expected)
    assert all(r.state_type.value == "COMPLETED" for r in runs)


def test_generate_dataset_flow__rerun_on_complete_store_writes_nothing(
    generated: dict[str, object], config_file: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def no_cluster(*_args: object) -> None:
        raise AssertionError("a complete store must not start a Dask cluster")

    monkeypatch.setattr(generate_dataset, "dask_task_runner", no_cluster)
    rerun = generate_dataset_flow(out=generated["path"], config_file=str(config_file), workers=2)
    assert rerun["chunks_written"] == 0 and rerun["rows_written"] == 0
    assert rerun["chunks_skipped"] == CHUNKS
    assert chunk_task_runs(rerun["flow_run_id"]) == []


def test_histogram_path__replaces_zarr_suffix() -> None:
    assert histogram_path("runs/x/dataset.zarr") == Path("runs/x/dataset.error_hist.png")
    assert histogram_path("runs/x/store") == Path("runs/x/store.error_hist.png")


def test_generate_dataset_flow__sensor_profile_sets_frequencies_and_noise(tmp_path: Path) -> None:
    """``sensor``, as ``mpi-lidar simulate --sensor``: the profile's sensor is simulated, over the preset."""
    profile = tmp_path / "sensor.toml"
    profile.write_text('schema = "mpi-lidar/sensor@1"\nfootprint_area_m2 = 0.02\nnoise_scale = 2.0\n'
                       "frequencies_hz = [10000000.0, 20000000.0, 30000000.0]\nrange_m = [1.0, 6.0]\n")
    result = generate_dataset_flow(out=str(tmp_path / "d.zarr"), samples=400, workers=0, sensor=str(profile))
    config = dataset.store_config(dataset.open_store(tmp_path / "d.zarr"))
    assert config.frequencies_hz == (10e6, 20e6, 30e6) and config.simulator.noise_scale == 2.0
    assert result["config_sha256"] == config_sha256(config)
