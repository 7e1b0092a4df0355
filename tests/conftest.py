from __future__ import annotations

import os
import uuid
from pathlib import Path

import numpy as np
import pytest

from mpi_lidar.config import Config, PriorConfig

POSTGRES_ADMIN_URL = os.environ.get("MPI_LIDAR_TEST_POSTGRES", "postgresql://postgres@127.0.0.1:5432/postgres")

TESTS = Path(__file__).resolve().parent

# Every test is either `unit` (pure functions on small inputs; `make test-quick` runs these, in under two minutes)
# or `integration`. A test is integration when it says so itself (@pytest.mark.integration) or carries `slow`,
# lives in one of INTEGRATION_PATHS, uses one of INTEGRATION_FIXTURES (a Dask cluster, a dataset or model trained
# through one, PostgreSQL, the Prefect API, a browser, command-line runs in subprocesses), is named for a
# command-line run or a benchmark (`test_<command>_cli__<case>`, `..._benchmark...`), or is one of SLOW_TESTS;
# everything else is unit.
INTEGRATION_PATHS = (
    "integration/", "flows/",  # Dask processes, PostgreSQL, the Prefect API and flow runs
    "cli/test_readme_commands.py",  # every command of the README, as a user runs it
    "workflows/test_bench.py", "workflows/test_benchmark_correction.py",  # the benchmarks
)
INTEGRATION_FIXTURES = frozenset({
    "cluster_client", "small_dataset", "small_model", "postgres_url",  # this file
    "dask_cluster", "cluster_model", "pg_database",  # tests/integration/conftest.py
    "prefect_api", "dask_scheduler",  # tests/flows/conftest.py
    "two_worker_client", "waveform_reference",  # tests/simulation/test_dataset.py
    "runs",  # tests/cli/test_cli_simulate.py: `mpi-lidar simulate` in subprocesses
    "chromium",  # tests/reporting/test_browser.py
})
INTEGRATION_NAMES = ("_cli__", "benchmark")
# In-process but slow: 2 s or more each on two cores (scenes rendered, fitted and corrected at full size, outputs
# written with figures). `make test-quick` leaves them to `make test`; the names, not the files, so a test keeps
# its kind when its file is split or renamed.
SLOW_TESTS = frozenset({
    # correction/footprint/test_estimate.py
    "test_calibrate__pools_scans_writes_a_profile_that_correct_records",
    "test_calibration_diagnosis__the_surfaces_beyond_the_view_carry_the_strong_multipath",
    "test_correct__a_significant_estimate_is_used_and_reported",
    "test_correct__an_estimate_that_is_not_significant_leaves_its_pixels_as_measured",
    "test_estimate__against_a_reference_depth_finds_the_renders_footprint",
    "test_estimate__from_the_scans_own_surfaces_at_a_small_footprint",
    "test_estimate__strong_multipath_on_a_near_corner_is_read_within_1_5x",
    "test_estimate__three_surfaces_of_a_room_corner_measure_the_footprint",
    "test_light_free_albedo__far_blocks_are_those_the_model_couples_least",
    "test_light_free_albedo__strong_multipath_is_taken_off_the_boards_amplitude",
    "test_scan_footprint__a_scan_without_geometry_measures_nothing",
    # correction/footprint/test_partners.py
    "test_estimate__a_corner_without_multipath_measures_no_footprint",
    "test_estimate__strong_multipath_bends_the_boards_but_not_the_partner_planes",
    "test_estimate__strong_multipath_finds_the_least_residuals_not_the_first_fixed_point",
    "test_nearest_surface__a_block_across_the_edge_gives_each_pixel_its_own_wall",
    "test_nearest_surface__on_a_shallow_corner_no_pixel_is_read_on_the_plane_behind_its_wall",
    "test_nearest_surface__past_a_bent_edge_the_pixels_go_to_the_wall_they_lie_on",
    # correction/test_tiling.py
    "test_correct_scan__tiled_equals_untiled_to_the_last_bit",
    "test_correct_scan__working_memory_grows_by_a_few_bytes_a_pixel_when_tiled",
    # learning/test_model_range.py
    "test_command__prints_the_table",
    # reporting/test_scan_outputs.py
    "test_full__archived_scan_writes_maps_named_point_clouds_and_the_3d_view",
    "test_import__reporting_leaves_the_matplotlib_backend_alone",
    "test_output_level__is_no_part_of_the_hash_a_higher_level_is_kept_a_lower_one_completed",
    "test_output_level__scan_without_geometry_at_full_says_point_clouds_were_skipped",
    "test_write_scan_outputs__a_users_open_pyplot_figure_survives",
    "test_write_scan_outputs__each_level_writes_its_files_and_says_which",
    # scans/test_geometry.py
    "test_equivalent_rho_aba__follows_the_renderer_and_the_partner_albedo",
    "test_multipath_potential__corner_grows_towards_the_edge_and_agrees_with_the_renderer",
    # scans/test_stored_map.py
    "test_correct_scan__stored_maps_correct_to_the_last_bit_as_in_memory",
    "test_process_scan__a_scan_above_the_threshold_is_read_from_its_store_with_the_same_outputs",
    "test_scan_metrics__banded_sums_match_the_whole_map_within_rounding",
    # simulation/test_scenes.py
    "test_render__cornered_board_matches_the_papers_fig7_magnitude",
    # test_hostile_inputs.py
    "test_dataset_reader__hostile_stores",
    "test_scan_reader__hostile_stores",
    # workflows/test_correct_overhead.py
    "test_archive_scans__every_thread_allocates_from_one_heap",
})


def marker_kind(item: pytest.Item) -> str:
    """``"unit"`` or ``"integration"`` for one collected test (the rules above)."""
    own = {mark.name for mark in item.iter_markers()} & {"unit", "integration"}
    if len(own) == 1:
        return own.pop()
    if own:
        raise pytest.UsageError(f"{item.nodeid} is marked both unit and integration")
    relative = Path(str(item.path)).resolve().relative_to(TESTS).as_posix()
    name = getattr(item, "originalname", item.name)
    if (relative.startswith(INTEGRATION_PATHS) or item.get_closest_marker("slow") is not None
            or INTEGRATION_FIXTURES.intersection(getattr(item, "fixturenames", ()))
            or any(part in name for part in INTEGRATION_NAMES) or name in SLOW_TESTS):
        return "integration"
    return "unit"


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        kind = marker_kind(item)
        if item.get_closest_marker(kind) is None:
            item.add_marker(kind)


@pytest.fixture
def config() -> Config:
    return Config()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def cluster_client():
    """One two-worker LocalCluster (worker processes, one thread each) shared by the session."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        with Client(cluster) as client:
            yield client


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory) -> Path:
    """A complete 8,000-row dataset (6,400 train, 1,600 test) of the paper's prior (d_AS 1.4-2.4 m): small
    models learn it well enough for the tests' scans at about 2 m, and its range rule is theirs."""
    from mpi_lidar.workflows.generate import generate

    path = tmp_path_factory.mktemp("small") / "dataset.zarr"
    generate(path, Config(prior=PriorConfig()).replace(dataset={"samples": 8_000, "chunk_rows": 2_000, "seed": 11}))
    return path


@pytest.fixture
def postgres_url():
    """A fresh PostgreSQL database on the local server, dropped afterwards."""
    import psycopg

    name = f"mpi_lidar_test_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(POSTGRES_ADMIN_URL, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"')
    yield POSTGRES_ADMIN_URL.rsplit("/", 1)[0] + f"/{name}"
    with psycopg.connect(POSTGRES_ADMIN_URL, autocommit=True) as admin:
        admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


@pytest.fixture(scope="session")
def small_model(tmp_path_factory, cluster_client, small_dataset) -> Path:
    """A quickly trained residual model on the small dataset (through xgboost.dask)."""
    from mpi_lidar.learning.features import FeatureSpec
    from mpi_lidar.learning.train import train_and_save

    params = {"max_depth": 6, "learning_rate": 0.3, "subsample": 1.0, "colsample_bytree": 1.0,
              "min_child_weight": 1.0, "reg_lambda": 1.0, "gamma": 0.0}
    out, _ = train_and_save(cluster_client, small_dataset, tmp_path_factory.mktemp("model") / "model",
                            FeatureSpec(Config().frequencies_hz, "raw", "residual"), params,
                            num_boost_round=150, early_stopping_rounds=10)
    return out
