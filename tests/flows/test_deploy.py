"""The nightly-regeneration deployment: built in Python for `serve`, declared in infra/prefect.yaml for workers."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
import yaml
from prefect.flows import load_flow_from_entrypoint
from prefect.settings import PREFECT_API_URL, temporary_settings

from flows import deploy
from flows.deploy import build_deployments, on_demand_deployments
from flows.regenerate import regenerate_dataset_flow
from mpi_lidar import cli
from mpi_lidar.errors import EXIT_USER_ERROR

REPO = Path(__file__).resolve().parents[2]
ENTRYPOINT = "flows/regenerate.py:regenerate_dataset_flow"


def prefect_yaml_deployments() -> list[dict]:
    return yaml.safe_load((REPO / "infra" / "prefect.yaml").read_text())["deployments"]


def nightly_spec() -> dict:
    return {d["name"]: d for d in prefect_yaml_deployments()}["nightly-regeneration"]


def test_build_deployments__nightly_cron_entrypoint_and_parameters(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)  # entrypoints are relative to the directory deployments are made from
    (deployment,) = build_deployments(root="runs/nightly", cron="0 2 * * *", preset="quick")
    assert deployment.name == "nightly-regeneration" and deployment.flow_name == "regenerate-dataset"
    assert deployment.entrypoint == ENTRYPOINT
    assert [s.schedule.cron for s in deployment.schedules] == ["0 2 * * *"]
    assert deployment.parameters == {"root": "runs/nightly", "preset": "quick", "workers": 2}


def test_build_deployments__passes_scheduler_address(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)
    (deployment,) = build_deployments("/data/nightly", "30 3 * * 1", "paper", scheduler="tcp://dask:8786")
    assert deployment.parameters["scheduler"] == "tcp://dask:8786" and deployment.parameters["preset"] == "paper"
    assert deployment.schedules[0].schedule.cron == "30 3 * * 1"


def test_main__refuses_to_serve_without_a_server(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def no_serve(*_args: object) -> None:
        raise AssertionError("must not serve on an ephemeral API")

    monkeypatch.setattr(deploy, "serve", no_serve)
    with temporary_settings(updates={PREFECT_API_URL: None}), pytest.raises(SystemExit) as exit_info:
        deploy.main(["--root", "runs/nightly"])
    assert exit_info.value.code == EXIT_USER_ERROR == cli.EXIT_USER_ERROR
    assert "PREFECT_API_URL" in capsys.readouterr().err


def test_main__serves_the_built_deployment_with_an_absolute_root(monkeypatch: pytest.MonkeyPatch) -> None:
    served: list[object] = []
    monkeypatch.setattr(deploy, "serve", lambda *deployments: served.extend(deployments))
    monkeypatch.chdir(REPO)
    deploy.main(["--root", "runs/nightly", "--cron", "15 1 * * *", "--workers", "1"])
    deployment, *on_demand = served
    assert [d.name for d in on_demand] == ["tune", "train", "correct-archive"]
    assert deployment.parameters["root"] == str(REPO / "runs" / "nightly")
    assert deployment.parameters["workers"] == 1 and deployment.schedules[0].schedule.cron == "15 1 * * *"


def test_prefect_yaml__entrypoint_loads_the_regeneration_flow(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)  # `prefect deploy --prefect-file infra/prefect.yaml` runs from the repository root
    spec = nightly_spec()
    path, function = spec["entrypoint"].split(":")
    assert (REPO / path).is_file() and spec["entrypoint"] == ENTRYPOINT
    flow = load_flow_from_entrypoint(spec["entrypoint"])
    assert flow.name == regenerate_dataset_flow.name and flow.fn.__name__ == function


def test_prefect_yaml__schedule_parameters_and_work_pool() -> None:
    spec = nightly_spec()
    assert spec["name"] == "nightly-regeneration"
    assert [s["cron"] for s in spec["schedules"]] == ["0 2 * * *"]
    accepted = inspect.signature(regenerate_dataset_flow.fn).parameters
    assert set(spec["parameters"]) <= set(accepted) and "root" in spec["parameters"]
    assert spec["work_pool"]["name"] == "local"


def test_on_demand_deployments__tune_train_correct_with_cluster_parameters(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)
    deployments = on_demand_deployments(workers=3, scheduler="tcp://dask:8786")
    assert [d.entrypoint for d in deployments] == [
        "flows/tune.py:tune_flow", "flows/train.py:train_flow", "flows/correct.py:correct_archive_flow"]
    assert [d.parameters for d in deployments] == [{"workers": 3, "scheduler": "tcp://dask:8786"}] * 2 + [
        {"scheduler": "tcp://dask:8786"}], "correction runs in the flow's process unless told, as mpi-lidar correct"
    assert not any(d.schedules for d in deployments)
    assert on_demand_deployments(workers=3)[2].parameters == {}
    in_yaml = {d["name"]: d["entrypoint"] for d in prefect_yaml_deployments()}
    assert {d.entrypoint for d in deployments} <= set(in_yaml.values())


def test_prefect_yaml__every_entrypoint_loads(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)
    for spec in prefect_yaml_deployments():
        flow = load_flow_from_entrypoint(spec["entrypoint"])
        assert set(spec["parameters"]) <= set(inspect.signature(flow.fn).parameters), spec["name"]


def test_on_demand_deployments__correction_schema_has_every_correct_option(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every option of `mpi-lidar correct` can be set on the correction deployment when it is triggered."""
    monkeypatch.chdir(REPO)
    correction = {d.name: d for d in on_demand_deployments()}["correct-archive"]
    schema = correction._parameter_openapi_schema
    properties = schema.properties
    assert {"scans", "model", "out", "gate", "min_bias_mm", "footprint_area_m2", "workers", "scheduler"} <= set(
        properties)
    assert set(schema.required) == {"scans", "model", "out"}
    gate = schema.definitions[properties["gate"]["$ref"].rsplit("/", 1)[-1]]  # the enum GateName, by reference
    assert gate["enum"] == ["geometry", "all", "consistency"]
    assert properties["gate"]["default"] == "geometry" and properties["min_bias_mm"].get("default") is None
    cli_options = {param.name for param in cli.cli.commands["correct"].params}
    assert cli_options - {"model_dir", "out_dir"} <= set(properties)


def test_docs__every_prefect_server_start_command_turns_telemetry_off() -> None:
    """A server started as documented prints no telemetry error: the variable is set in its shell block."""
    pages = [REPO / "docs" / "how-to" / "prefect.md", REPO / "infra" / "README.md"]
    started = 0
    for page in pages:
        for block in page.read_text().split("```")[1::2]:
            if "prefect server start" in block:
                started += 1
                assert "PREFECT_SERVER_ANALYTICS_ENABLED=false" in block, f"{page.name}: {block}"
    assert started >= 3
