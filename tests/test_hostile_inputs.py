"""Hostile inputs: every reader of a user's file answers with one clear error, or with valid data.

Hypothesis drives the readers of configurations, dataset stores, scan stores, .npz imports and model cards
with malformed input. Each reader either returns a valid object or raises an :class:`MpiLidarError` (one
line: what, where, what to do); no other exception type may escape. Where a command reads the file, the
command exits 2 with one ``error:`` line and writes nothing. ``HOSTILE_EXAMPLES`` inputs per reader, and
the number of readers, give the count docs/how-to/dask-cluster.md quotes.
"""

from __future__ import annotations

import errno
import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mpi_lidar.calibration.profile import read_profile
from mpi_lidar.cli import path_fault
from mpi_lidar.config import Config, load_config
from mpi_lidar.correction.options import MAX_FOOTPRINT_AREA_M2
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.model import CARD_FILE, load_model
from mpi_lidar.locations import driver_url
from mpi_lidar.scans.importers import load_npz
from mpi_lidar.scans.store import read_scan, write_scan
from mpi_lidar.simulation import dataset
from mpi_lidar.workflows.verify import verify_store
from tests.cli_runner import assert_one_error_line, call_main
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

HOSTILE_EXAMPLES = 60
hostile = settings(max_examples=HOSTILE_EXAMPLES, deadline=None, derandomize=True,
                   suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                          HealthCheck.data_too_large])

SCALARS = st.one_of(
    st.integers(min_value=-(2**70), max_value=2**70), st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(), st.text(max_size=12), st.none(),
)
JSON_VALUES = st.recursive(SCALARS, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
    st.text(max_size=8), inner, max_size=4), max_leaves=8)


# --- configurations ----------------------------------------------------------------------------------------

FIELDS = {
    "": ["frequencies_hz"],
    "sensor": ["gamma_r_v2", "transit_time_s", "integration_time_s", "avalanche_gain", "temperature_k"],
    "prior": ["scheme", "d_as_m", "d_ab_m", "albedo", "no_multipath_fraction"],
    "simulator": ["fidelity", "noise_scale", "round_photons", "whole_cycles", "tia_noise_mean_electrons"],
    "dataset": ["samples", "chunk_rows", "seed", "test_fraction"],
}


def toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return json.dumps(str(value))


TOML_SCALARS = st.one_of(st.integers(min_value=-(2**62), max_value=2**62), st.floats(), st.booleans(),
                         st.text(max_size=10))
TOML_VALUES = st.one_of(TOML_SCALARS, st.lists(TOML_SCALARS, max_size=5))


@st.composite
def hostile_toml(draw) -> str:
    lines = []
    for section, names in FIELDS.items():
        chosen = draw(st.lists(st.sampled_from([*names, "bogus_field"]), unique=True, max_size=3))
        if not chosen:
            continue
        if section:
            lines.append(f"[{section}]")
        lines += [f"{name} = {toml_value(draw(TOML_VALUES))}" for name in chosen]
    if draw(st.booleans()):
        lines.append(draw(st.text(max_size=20)))  # trailing junk: often not TOML at all
    return "\n".join(lines) + "\n"


# Hypothesis notes a change of the global `random` state while it draws an example, whoever made it. The
# strategy draws nothing from `random`, but the threads that the previous example's simulate command left
# behind (Dask's and Prefect's, which jitter with `random`) can run just then.
@pytest.mark.unit
@pytest.mark.filterwarnings("ignore:Do not use the `random` module inside strategies"
                            ":hypothesis.errors.HypothesisDeprecationWarning")
@hostile
@given(text=hostile_toml())
def test_config_reader__hostile_toml(tmp_path_factory, monkeypatch, capsys, text):
    work = tmp_path_factory.mktemp("config")
    path = work / "hostile.toml"
    path.write_text(text)
    try:
        load_config(path)
    except MpiLidarError as exc:
        assert "\n" not in str(exc)
        out = work / "d.zarr"
        code, _, stderr = call_main(monkeypatch, capsys, "simulate", "--out", out, "--config", path,
                                         "--samples", 50, "--workers", 0)
        assert code == 2
        assert_one_error_line(stderr)
        assert sorted(p.name for p in work.iterdir()) == ["hostile.toml"]


# --- sensor profiles ---------------------------------------------------------------------------------------

PROFILE_FIELDS = ["footprint_area_m2", "saturation_amplitude_v2", "min_amplitude_sigmas", "amplitude_scale",
                  "frequencies_hz", "noise_scale", "range_m", "frequency_offsets_m", "bogus_field"]


@st.composite
def hostile_profile(draw) -> str:
    lines = [] if draw(st.booleans()) else ['schema = "mpi-lidar/sensor@1"']
    for name in draw(st.lists(st.sampled_from(PROFILE_FIELDS), unique=True, max_size=4)):
        lines.append(f"{name} = {toml_value(draw(TOML_VALUES))}")
    if draw(st.booleans()):
        lines.append(f"footprint_area_m2 = {toml_value(draw(TOML_SCALARS))}")
    return "\n".join(lines) + "\n"


@pytest.mark.unit
@hostile
@given(text=hostile_profile())
def test_profile_reader__hostile_toml(tmp_path_factory, text):
    """Either a profile whose every number is a strict number within its physical bounds, or one line."""
    path = tmp_path_factory.mktemp("profile") / "sensor.toml"
    path.write_text(text)
    try:
        profile = read_profile(path)
    except MpiLidarError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
        return
    assert 0 < profile.footprint_area_m2 <= MAX_FOOTPRINT_AREA_M2
    assert not isinstance(profile.footprint_area_m2, bool)
    assert all(f > 0 for f in profile.frequencies_hz or ())
    assert profile.range_m is None or 0 < profile.range_m[0] < profile.range_m[1]


# --- .npz imports ------------------------------------------------------------------------------------------

DTYPES = st.sampled_from(["float32", "float64", "int16", "uint8", "bool", "complex64"])
NPZ_NAMES = st.sampled_from(["depth", "amplitude", "taps", "frequencies_hz", "reference_mask", "reference_depth",
                             "azimuth_rad", "elevation_rad", "unknown"])


@st.composite
def hostile_npz(draw) -> dict[str, np.ndarray]:
    arrays = {}
    for name in draw(st.lists(NPZ_NAMES, unique=True, min_size=1, max_size=5)):
        shape = tuple(draw(st.lists(st.integers(0, 5), max_size=4)))
        values = draw(st.sampled_from([0.0, 1.0, np.nan, -1.0, 2.0e6]))
        with np.errstate(invalid="ignore"):
            arrays[name] = np.full(shape, values).astype(draw(DTYPES))
    return arrays


@pytest.mark.unit
@hostile
@given(arrays=hostile_npz())
def test_npz_reader__hostile_archives(tmp_path_factory, monkeypatch, capsys, arrays):
    work = tmp_path_factory.mktemp("npz")
    path = work / "frame.npz"
    np.savez(path, **arrays)
    try:
        load_npz(path, (12.5e6, 18.75e6, 25e6, 31.25e6))
    except MpiLidarError as exc:
        assert "\n" not in str(exc)
        code, _, stderr = call_main(monkeypatch, capsys, "import-scan", path, "--out", work / "f.scan.zarr",
                                         "--frequencies", "12.5e6,18.75e6,25e6,31.25e6")
        assert code == 2
        assert_one_error_line(stderr)
        assert sorted(p.name for p in work.iterdir()) == ["frame.npz"]


# --- scan stores -------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scan_store(tmp_path_factory) -> Path:
    return write_scan(two_path_scan("frame", height=6, width=5), tmp_path_factory.mktemp("scan") / "f.scan.zarr")


MUTATIONS = st.sampled_from(["attr", "array", "chunk", "metadata", "delete"])
SCAN_ARRAYS = st.sampled_from(["depth", "amplitude", "reference_mask", "reference_depth", "azimuth_rad"])


def _mutate_store(store: Path, draw, arrays) -> None:
    kind = draw(MUTATIONS)
    group = zarr.open_group(store=str(store), mode="r+")
    if kind == "attr":
        group.attrs[draw(st.sampled_from(["frequencies_hz", "name", "schema", "chunk_sha256", "scene",
                                          "samples", "chunk_rows", "config"]))] = draw(JSON_VALUES)
    elif kind == "array":
        name = draw(arrays)
        del group[name]
        shape = tuple(draw(st.lists(st.integers(0, 6), max_size=4)))
        group.create_array(name, data=np.zeros(shape, dtype=draw(DTYPES)))
    elif kind == "chunk":
        files = sorted(p for p in (store / draw(arrays)).rglob("*") if p.is_file() and p.name != "zarr.json")
        if files:
            target = files[draw(st.integers(0, len(files) - 1))]
            target.write_bytes(draw(st.binary(max_size=64)))
    elif kind == "metadata":
        meta = store / draw(arrays) / "zarr.json"
        if meta.exists():
            meta.write_text(draw(st.text(max_size=40)))
    else:
        shutil.rmtree(store / draw(arrays), ignore_errors=True)


@pytest.mark.integration
@pytest.mark.slow
@hostile
@given(data=st.data())
def test_scan_reader__hostile_stores(tmp_path_factory, scan_store, data):
    copy = tmp_path_factory.mktemp("scan") / "f.scan.zarr"
    shutil.copytree(scan_store, copy)
    _mutate_store(copy, data.draw, SCAN_ARRAYS)
    for read in (read_scan, verify_store):
        try:
            read(copy)
        except MpiLidarError as exc:
            assert "\n" not in str(exc)


# --- dataset stores ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def dataset_store(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("dataset") / "d.zarr"
    config = Config().replace(dataset={"samples": 400, "chunk_rows": 200, "seed": 1})
    dataset.create_store(path, config)
    for index in range(2):
        dataset.write_chunk(path, config, index)
    return path


@pytest.mark.integration
@pytest.mark.slow
@hostile
@given(data=st.data())
def test_dataset_reader__hostile_stores(tmp_path_factory, dataset_store, data):
    copy = tmp_path_factory.mktemp("dataset") / "d.zarr"
    shutil.copytree(dataset_store, copy)
    _mutate_store(copy, data.draw, st.sampled_from(["features", "target", "theta", "split", "chunk_done",
                                                    "chunk_sha256"]))
    for read in (dataset.dataset_info, lambda p: dataset.read_subsample(p, "test"), verify_store,
                 lambda p: dataset.read_lazy(p).features.sum().compute()):
        try:
            read(copy)
        except MpiLidarError as exc:
            assert "\n" not in str(exc)


# --- model cards -------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    return tiny_model(tmp_path_factory.mktemp("model") / "model", geometric=False, feature_set="raw", rounds=5)


def _paths(value: object, prefix: tuple = ()) -> list[tuple]:
    found = [prefix] if prefix else []
    if isinstance(value, dict):
        for key, inner in value.items():
            found += _paths(inner, (*prefix, key))
    return found


@pytest.mark.integration
@hostile
@given(data=st.data())
def test_card_reader__hostile_cards(tmp_path_factory, monkeypatch, capsys, model_dir, small_dataset, data):
    copy = tmp_path_factory.mktemp("card") / "model"
    shutil.copytree(model_dir, copy)
    card = json.loads((copy / CARD_FILE).read_text())
    how = data.draw(st.sampled_from(["delete", "replace", "truncate", "whole"]))
    if how == "whole":
        text = json.dumps(data.draw(JSON_VALUES))
    elif how == "truncate":
        full = json.dumps(card)
        text = full[: data.draw(st.integers(0, len(full) - 1))]
    else:
        path = data.draw(st.sampled_from(_paths(card)))
        holder = card
        for key in path[:-1]:
            holder = holder[key]
        if how == "delete":
            del holder[path[-1]]
        else:
            holder[path[-1]] = data.draw(JSON_VALUES)
        text = json.dumps(card)
    (copy / CARD_FILE).write_text(text)
    try:
        load_model(copy)
    except MpiLidarError as exc:
        assert "\n" not in str(exc)
        report = copy.parent / "report"
        code, _, stderr = call_main(monkeypatch, capsys, "evaluate", "--data", small_dataset, "--model", copy,
                                         "--report", report)
        assert code == 2
        assert_one_error_line(stderr)
        assert not report.exists()


# --- errors that are the user's: one line, no secret ----------------------------------------------------------


@pytest.mark.unit
@pytest.mark.parametrize("url", ["postgresql://bob:s@cretD@127.0.0.1:1/db", "postgresql://bob:s%40cretD@127.0.0.1:1/db",
                                 "postgresql://bob:pa:ss/w?rd#@127.0.0.1:1/db"])
def test_driver_url__a_password_is_encoded_before_the_driver_parses_it(url):
    from sqlalchemy.engine import make_url

    parsed = make_url(driver_url(url))
    assert parsed.host == "127.0.0.1" and parsed.port == 1 and parsed.username == "bob"
    assert parsed.password in ("s@cretD", "pa:ss/w?rd#")


@pytest.mark.integration
@pytest.mark.parametrize(("url", "secret"), [("postgresql://bob:s@cretD@127.0.0.1:1/db", "cretD"),
                                             ("postgresql://bob@127.0.0.1:1/db?PASSWORD=hunter22", "hunter22")])
def test_tune__a_storage_url_fails_in_one_line_showing_no_part_of_the_password(tmp_path, monkeypatch, capsys,
                                                                             small_dataset, url, secret):
    code, _, stderr = call_main(monkeypatch, capsys, "tune", "--data", small_dataset, "--storage", url,
                                "--trials", 1)
    assert code == 2
    assert_one_error_line(stderr, "Optuna storage")
    assert secret not in stderr and "unexpected" not in stderr


@pytest.mark.unit
def test_path_fault__a_path_past_the_limit_is_one_short_line(tmp_path, monkeypatch, capsys):
    long = tmp_path / ("d" * 300) / "a.scan.zarr"
    code, _, stderr = call_main(monkeypatch, capsys, "verify", long)
    assert code == 2
    assert_one_error_line(stderr)
    assert len(stderr) < 400 and "unexpected" not in stderr
    fault = path_fault(OSError(errno.ENAMETOOLONG, "File name too long", "/x" * 4000))
    assert fault is not None and "8,000 characters" in str(fault) and len(str(fault)) < 300


# --- flows fail like the command line --------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.parametrize(("args", "fragment"), [
    (["nope"], "unknown flow 'nope'"),
    (["correct-archive", "--scans", "a", "--model", "m", "--out", "o", "--gate", "nope"], "invalid choice: 'nope'"),
    (["correct-archive", "--scans", "a", "--model", "m", "--out", "o", "--bogus", "1"], "unrecognized arguments"),
    (["correct-archive", "--scans", "a", "--model", "m", "--out", "o", "--amplitude-scale", "0"], "amplitude_scale"),
    (["generate-dataset", "--out", "d.zarr", "--samples", "-5"], "dataset.samples"),
])
def test_flows__bad_options_are_one_error_line_exit_2_before_a_run(tmp_path, args, fragment):
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "flows", *args], capture_output=True, text=True, cwd=Path.cwd(),
                          timeout=300, env={**os.environ, "PREFECT_API_URL": "http://127.0.0.1:9/api"})
    assert done.returncode == 2, done.stderr
    assert_one_error_line(done.stderr, fragment)
    assert done.stdout == ""
