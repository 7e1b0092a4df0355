"""``python -m flows FLOW ...``, the documented way to run each flow locally: every flow's command runs on small
sizes in a process of its own, prints its result as JSON, keeps its console free of INFO and telemetry lines,
and every artifact it publishes has a key.

The commands run with the environment a user has: the session's quiet Prefect and Dask settings
(:mod:`tests.flows.environment`) are taken out, so what keeps the console quiet is the command's own defaults.
All but one report to the session's API, where the test reads their artifacts back; the correction command also
runs once with a temporary server of its own, as a first run on a new machine does.
"""

from __future__ import annotations

import inspect
import json
import os
import re
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from uuid import UUID

import click
import pytest
from prefect import get_client
from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterFlowRunId
from prefect.client.schemas.objects import Artifact

import flows.__main__ as runner
from flows.correct import SUMMARY_ARTIFACT_KEY, TABLE_ARTIFACT_KEY, artifact_slugs
from mpi_lidar import cli
from mpi_lidar.learning import tune
from mpi_lidar.learning.features import DEFAULT_FEATURE_SET, DEFAULT_GEOMETRIC, DEFAULT_TARGET_MODE, FeatureSpec
from mpi_lidar.scans.store import SCAN_SUFFIX, write_scan
from mpi_lidar.simulation.dataset import dataset_info
from mpi_lidar.simulation.scenes import DEMO_SCENES
from tests.fast_trials import TUNE_ROWS, queue_fast_trials
from tests.flows.helpers import subflow_runs
from tests.scan_factory import two_path_scan

REPO = Path(__file__).resolve().parents[2]
COMMAND_TIMEOUT_S = 600
# What the console of a local run must not show: INFO lines (Prefect's or Dask's), the telemetry error of an
# offline server, the port-8787 warning and the jupyter-server-proxy hint of a Dask scheduler, tracebacks.
NOISE = re.compile(r"\bINFO\b|telemetry|8787|jupyter-server-proxy|Traceback", re.IGNORECASE)
ARTIFACT_KEY = re.compile(r"^[a-z0-9-]+$")
# The flow beside the command it stands for, and parameters whose CLI default is spelled otherwise for the same
# behaviour: tune --geometric unset is the default.
FLOW_COMMANDS = {"generate-dataset": "simulate", "tune": "tune", "train": "train", "evaluate": "evaluate",
                 "table-2": "table2", "correct-archive": "correct", "pipeline": "pipeline"}
CLI_NAMES = {"preset_name": "preset", "study_name": "study", "target_mode": "target", "model_dir": "model",
             "out_dir": "out", "report_dir": "report"}
SAME_DEFAULT = {("tune", "geometric"): (None, DEFAULT_GEOMETRIC)}


def run_command(flow: str, *options: str, home: Path, api: str | None) -> tuple[dict[str, object], str]:
    """``python -m flows FLOW OPTIONS`` from the repository root; its printed JSON and its stderr.

    ``api`` None: the command starts its own temporary server, in ``home``.
    """
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_", "DASK_")) and k != "DO_NOT_TRACK"}
    env["PREFECT_HOME"] = str(home)
    if api:
        env["PREFECT_API_URL"] = api
    done = subprocess.run([sys.executable, "-m", "flows", flow, *options], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=COMMAND_TIMEOUT_S)
    assert done.returncode == 0, f"exit {done.returncode}\n{done.stderr[-4000:]}"
    return json.loads(done.stdout), done.stderr


def assert_quiet(stderr: str) -> None:
    noisy = [line for line in stderr.splitlines() if NOISE.search(line)]
    assert not noisy, "\n".join(noisy[:20])


def run_artifacts(flow_run_id: str, subflows: bool = False) -> list[Artifact]:
    """Every artifact of the flow run (and of its subflow runs), whatever its key."""
    ids = [UUID(flow_run_id)] + ([run.id for run in subflow_runs(flow_run_id)] if subflows else [])
    with get_client(sync_client=True) as client:
        return client.read_artifacts(artifact_filter=ArtifactFilter(flow_run_id=ArtifactFilterFlowRunId(any_=ids)))


def assert_keyed(found: list[Artifact]) -> set[str]:
    """Every artifact has a valid Prefect key; returns the keys."""
    assert found, "the run published no artifact"
    keys = [a.key for a in found]
    assert all(k is not None and ARTIFACT_KEY.match(k) for k in keys), keys
    return set(keys)


@pytest.fixture(scope="module")
def home(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("prefect-home")


@pytest.fixture(scope="module")
def port_8787_taken() -> Iterator[None]:
    """Port 8787, Dask's dashboard default, held by someone else (as on a machine with another cluster)."""
    with socket.socket() as sock:
        try:
            sock.bind(("127.0.0.1", 8787))
            sock.listen()
        except OSError:
            pass  # already taken, which is the case under test
        yield


@pytest.fixture(scope="module")
def generated(tmp_path_factory, config_file: Path, home: Path, prefect_api: str,
              port_8787_taken: None) -> tuple[dict[str, object], str]:
    """The generation command on a one-process LocalCluster: the flows' Dask path."""
    out = tmp_path_factory.mktemp("data") / "dataset.zarr"
    return run_command("generate-dataset", "--out", str(out), "--config-file", str(config_file), "--workers", "1",
                       home=home, api=prefect_api)


@pytest.fixture(scope="module")
def trained(generated, tmp_path_factory, home: Path, prefect_api: str) -> dict[str, object]:
    """Tuning (two queued fast trials) and training commands on the generated dataset."""
    data = generated[0]["result"]["path"]
    root = tmp_path_factory.mktemp("learned")
    storage = f"sqlite:///{root / 'optuna.db'}"
    spec = FeatureSpec(dataset_info(data).frequencies_hz, DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE, DEFAULT_GEOMETRIC)
    queue_fast_trials(tune.open_study(storage, "commands", tune.TuneSettings(data, spec, tune_rows=TUNE_ROWS)), 2)
    tuned, tune_err = run_command("tune", "--data", data, "--storage", storage, "--study", "commands", "--trials", "2",
                                  "--tune-rows", str(TUNE_ROWS), "--workers", "0", home=home, api=prefect_api)
    model, train_err = run_command("train", "--data", data, "--out", str(root / "model"), "--study", "commands",
                                   "--storage", storage, "--workers", "0", home=home, api=prefect_api)
    return {"data": data, "model": model["result"]["model_dir"], "runs": [tuned, model],
            "stderr": [tune_err, train_err]}


@pytest.fixture(scope="module")
def archive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("archive")
    for index, name in enumerate(("North_Wall", "south")):
        write_scan(two_path_scan(name, seed=index), root / f"{name}.scan.zarr")
    return root


def test_build_parser__every_flow_parameter_is_an_option_with_the_flows_default() -> None:
    for name in runner.FLOWS:
        flow = runner.load_flow(name)
        parameters = inspect.signature(flow.fn).parameters.values()
        required = [p.name for p in parameters if p.default is inspect.Parameter.empty]
        parsed = vars(runner.build_parser(name, flow).parse_args(
            [arg for p in required for arg in (f"--{p.replace('_', '-')}", "x")]))
        assert parsed.pop("debug") is False
        assert set(parsed) == {p.name for p in parameters}, name
        for p in parameters:
            expected = ("x", ["x"]) if p.name in required else (p.default,)
            assert parsed[p.name] in expected, (name, p.name, parsed[p.name])


def test_build_parser__reads_numbers_choices_lists_and_flags_as_the_cli_does() -> None:
    parser = runner.build_parser("correct-archive", runner.load_flow("correct-archive"))
    args = parser.parse_args(["--scans", "a", "b", "--scans", "c", "--model", "m", "--out", "o", "--footprint-area-m2",
                              "auto", "--amplitude-scale", "4000", "--fail-on", "degraded", "--fail-on", "unchanged",
                              "--point-cloud", "laz", "--allow-unserved", "--gate", "all", "--min-bias-mm", "1.5"])
    assert args.scans == ["a", "b", "c"] and args.footprint_area_m2 == "auto" and args.amplitude_scale == 4000.0
    assert args.fail_on == ["degraded", "unchanged"] and args.point_clouds == ["laz"] and args.allow_unserved is True
    assert args.gate == "all" and args.min_bias_mm == 1.5 and args.workers == 0
    with pytest.raises(SystemExit) as refused:
        parser.parse_args(["--scans", "a", "--model", "m", "--out", "o", "--gate", "everything"])
    assert refused.value.code == 2


@pytest.mark.parametrize("flow", sorted(FLOW_COMMANDS))
def test_flow_defaults__equal_the_command_lines(flow: str) -> None:
    """A parameter the flow shares with its ``mpi-lidar`` command has the command's default."""
    command = cli.cli.commands[FLOW_COMMANDS[flow]]
    required = [arg for p in command.params if p.required
                for arg in (["x"] if isinstance(p, click.Argument) else [p.opts[0], "x"])]
    with command.make_context(FLOW_COMMANDS[flow], required) as context:  # what the command's function receives
        cli_defaults = {CLI_NAMES.get(name, name): value for name, value in context.params.items()}
    flow_parameters = inspect.signature(runner.load_flow(flow).fn).parameters
    shared = set(cli_defaults) & set(flow_parameters)
    assert {"workers", "scheduler"} & shared or flow in ("evaluate", "table-2")
    for name in shared:
        ours = flow_parameters[name].default
        if ours is inspect.Parameter.empty:  # required by both
            continue
        theirs = cli_defaults[name]
        theirs = None if theirs in ((), []) else theirs
        if (flow, name) in SAME_DEFAULT:
            assert (theirs, ours) == SAME_DEFAULT[flow, name], name
        else:
            assert ours == theirs, f"{flow} {name}: flow {ours!r}, mpi-lidar {FLOW_COMMANDS[flow]} {theirs!r}"


def test_artifact_slugs__prefect_keys_unique_in_the_batch() -> None:
    assert artifact_slugs(["North_Wall", "north-wall", "a.b", "Ü"]) == ["north-wall", "north-wall-2", "a-b", "unnamed"]


def test_main__unknown_flow_and_bad_option_exit_2(capsys: pytest.CaptureFixture[str],
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    for name, value in runner.QUIET_ENVIRONMENT.items():  # main sets them where unset: keep them in this test
        monkeypatch.setenv(name, os.environ.get(name, value))
    assert runner.main(["no-such-flow"]) == 2
    assert "unknown flow 'no-such-flow'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as refused:
        runner.main(["evaluate", "--data", "d", "--model", "m", "--report", "r", "--split", "validation"])
    assert refused.value.code == 2


@pytest.mark.slow
@pytest.mark.integration
def test_generate_dataset_command__dask_workers_quiet_with_port_8787_taken(generated) -> None:
    printed, stderr = generated
    assert_quiet(stderr)
    assert printed["state"] == "Completed" and printed["result"]["chunks_written"] == 4
    assert dataset_info(printed["result"]["path"]).complete
    assert assert_keyed(run_artifacts(printed["flow_run_id"])) == {"dataset-summary"}


@pytest.mark.slow
@pytest.mark.integration
def test_tune_train_evaluate_table2_commands__quiet_and_keyed(trained, tmp_path: Path, home: Path,
                                                             prefect_api: str) -> None:
    for stderr in trained["stderr"]:
        assert_quiet(stderr)
    tuned, model = trained["runs"]
    assert tuned["result"]["trials_run"] == 2 and Path(model["result"]["model_dir"], "model.ubj").is_file()
    evaluated, evaluate_err = run_command("evaluate", "--data", trained["data"], "--model", trained["model"],
                                          "--out", str(tmp_path / "report"), home=home, api=prefect_api)
    # Table II compares pixel-wise estimators: without --model (the trained one is geometric) it fits its own.
    table, table_err = run_command("table-2", "--data", trained["data"], "--out", str(tmp_path / "t2"),
                                   "--trials", "1", "--train-rows", "500", "--svm-rows", "200",
                                   home=home, api=prefect_api)
    assert_quiet(evaluate_err)
    assert_quiet(table_err)
    assert "corrected (XGBoost)" in evaluated["result"] and "| SVM |" in table["result"]
    keys = [assert_keyed(run_artifacts(run["flow_run_id"])) for run in (tuned, model, evaluated, table)]
    assert keys == [{"tuning-study"}, {"model-card"}, {"evaluation"}, {"table-2"}]


@pytest.mark.slow
@pytest.mark.integration
def test_correct_archive_command__every_artifact_keyed(trained, archive: Path, tmp_path: Path, home: Path,
                                                       prefect_api: str) -> None:
    printed, stderr = run_command("correct-archive", "--scans", str(archive), "--model", trained["model"],
                                  "--out", str(tmp_path / "corrected"), "--allow-unserved", home=home, api=prefect_api)
    assert_quiet(stderr)
    assert set(printed["result"]["statuses"]) == {str(archive / "North_Wall.scan.zarr"),
                                                  str(archive / "south.scan.zarr")}
    keys = assert_keyed(run_artifacts(printed["flow_run_id"]))
    assert keys == {SUMMARY_ARTIFACT_KEY, TABLE_ARTIFACT_KEY, "scan-north-wall", "report-north-wall", "scan-south",
                    "report-south"}


@pytest.mark.slow
@pytest.mark.integration
def test_correct_archive_command__first_run_own_server_failed_scan_prints_json_and_one_error_line(
        trained, archive: Path, tmp_path: Path) -> None:
    """A first run on a new machine (no API configured, a new PREFECT_HOME: the command starts its own temporary
    server) where one scan of two is damaged: the one JSON object on stdout still holds the statuses of the scans
    that did succeed, for a wrapper to read, and stderr ends with one error line, no traceback."""
    broken = tmp_path / "broken.scan.zarr"
    broken.mkdir()
    (broken / "zarr.json").write_text("{not json")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_", "DASK_")) and k != "DO_NOT_TRACK"}
    env["PREFECT_HOME"] = str(tmp_path / "new-home")
    done = subprocess.run([sys.executable, "-m", "flows", "correct-archive", "--scans", str(broken),
                           str(archive / "south.scan.zarr"), "--model", trained["model"], "--out",
                           str(tmp_path / "out"), "--allow-unserved"], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=COMMAND_TIMEOUT_S)
    assert done.returncode == 1
    printed = json.loads(done.stdout)
    assert printed["state"] == "Failed" and printed["error"].startswith("1 of 2 scans failed")
    assert printed["result"]["statuses"][str(broken)] == "failed"
    assert printed["result"]["statuses"][str(archive / "south.scan.zarr")] != "failed"
    assert [p.parent.name for p in (tmp_path / "out").rglob("report.html") if p.parent.name != "summary"] == ["south"]
    assert done.stderr.splitlines()[-1].startswith("error: 1 of 2 scans failed")
    assert "Traceback" not in done.stderr


@pytest.mark.slow
@pytest.mark.integration
def test_regenerate_and_pipeline_commands__quiet_and_keyed(config_file: Path, tmp_path: Path, home: Path,
                                                           prefect_api: str) -> None:
    regenerated, regenerate_err = run_command("regenerate-dataset", "--root", str(tmp_path / "nightly"),
                                              "--config-file", str(config_file), "--workers", "0",
                                              home=home, api=prefect_api)
    assert_quiet(regenerate_err)
    assert regenerated["result"]["skipped"] is False and (tmp_path / "nightly" / "latest").is_symlink()
    assert assert_keyed(run_artifacts(regenerated["flow_run_id"], subflows=True)) == {"dataset-summary"}

    for name in DEMO_SCENES:  # kept by the pipeline as found: small scans, so the run is the flows', not the renderer's
        write_scan(two_path_scan(name, seed=len(name)), tmp_path / "run" / "scenes" / f"{name}{SCAN_SUFFIX}")
    piped, pipeline_err = run_command("pipeline", "--out", str(tmp_path / "run"), "--config-file", str(config_file),
                                      "--trials", "1", "--tune-rows", str(TUNE_ROWS), "--workers", "0",
                                      home=home, api=prefect_api)
    assert_quiet(pipeline_err)
    assert piped["result"]["corrected"] is True and (tmp_path / "run" / "model" / "card.json").is_file()
    keys = assert_keyed(run_artifacts(piped["flow_run_id"], subflows=True))
    assert {"dataset-summary", "tuning-study", "model-card", "evaluation", SUMMARY_ARTIFACT_KEY} <= keys


def test_build_parser__correct_archive_help_says_the_point_cloud_defaults_it_follows() -> None:
    text = " ".join(runner.build_parser("correct-archive", runner.load_flow("correct-archive")).format_help().split())
    assert "laz at light, ply and laz at full, none at data" in text and "none below" not in text
    assert "--point-cloud-frame {scanner,z-up}" in text and "--no-return-range" in text
