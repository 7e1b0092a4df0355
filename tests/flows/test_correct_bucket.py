"""The correct-archive flow on an archive in a bucket: scans read from and outputs published to a real
S3-compatible server (moto's, started here on 127.0.0.1), with keys that hold '@', ':' and '/' in the
environment and nowhere else: not in the flow run's parameters, logs or artifacts, nor in the outputs."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from urllib.parse import quote
from uuid import UUID

import pytest
from prefect import get_client
from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterFlowRunId, LogFilter, LogFilterFlowRunId
from prefect.client.schemas.objects import Artifact, Log, State
from prefect.logging.handlers import APILogHandler

from benchmarks.object_storage import aws_environment
from flows.correct import SUMMARY_ARTIFACT_KEY, correct_archive_flow
from mpi_lidar.locations import location
from mpi_lidar.scans.store import write_scan
from mpi_lidar.storage import objects
from mpi_lidar.storage.manifest import MANIFEST_FILE
from mpi_lidar.workflows.verify import verify_store
from tests.flows.helpers import wait_for
from tests.moto_server import moto_server
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.integration

SECRET = "fl0w@Secr:et/Key+9"  # the secret access key: '@', ':' and '/' in it
KEY_ID = "AKIA@FLOW:ID"  # no '/': an access key id is a field of the signature's slash-separated scope
BUCKET = "bucket"
SCANS = ("north", "south")
OUT = f"s3://{BUCKET}/out"


def probes() -> tuple[str, ...]:
    """The credentials as they could leak: whole, percent-encoded, and the secret's tail after its '/'."""
    return SECRET, quote(SECRET, safe=""), KEY_ID, quote(KEY_ID, safe=""), "et/Key+9"


def leaked(text: str) -> list[str]:
    return [probe for probe in probes() if probe in text]


@pytest.fixture(scope="module")
def bucket_server() -> Iterator[str]:
    """moto's S3 server in a thread of this process, on a free port of 127.0.0.1, the AWS variables pointing
    at it with :data:`KEY_ID` and :data:`SECRET`, and :data:`BUCKET` created: its endpoint URL."""
    with moto_server() as endpoint, aws_environment(endpoint, KEY_ID, SECRET):
        objects.filesystem(location(f"s3://{BUCKET}")).mkdir(BUCKET)
        yield endpoint


@pytest.fixture(scope="module")
def bucket_archive(bucket_server, tmp_path_factory) -> str:
    """Two scans of 24 x 32 uploaded to ``s3://bucket/scans/``: that URL."""
    local = tmp_path_factory.mktemp("archive") / "scans"
    for seed, name in enumerate(SCANS):
        write_scan(two_path_scan(name, seed=seed), local / f"{name}.scan.zarr")
    url = f"s3://{BUCKET}/scans/"
    objects.filesystem(location(url)).put(str(local) + "/", f"{BUCKET}/scans", recursive=True)
    return url


def flow_run_logs(flow_run_id: str) -> list[Log]:
    with get_client(sync_client=True) as client:
        return client.read_logs(log_filter=LogFilter(flow_run_id=LogFilterFlowRunId(any_=[UUID(flow_run_id)])))


def flow_run_artifacts(flow_run_id: str) -> list[Artifact]:
    with get_client(sync_client=True) as client:
        return client.read_artifacts(
            artifact_filter=ArtifactFilter(flow_run_id=ArtifactFilterFlowRunId(any_=[UUID(flow_run_id)])))


def bucket_files(url: str) -> dict[str, bytes]:
    """Every object under ``url``, by its key below it, with its bytes (the outputs are small)."""
    where = location(url)
    fs = objects.filesystem(where)
    keys = fs.find(where.path)
    return {key.removeprefix(where.path + "/"): fs.cat_file(key) for key in keys}


class Recorded(logging.Handler):
    """Every record it is handed, formatted (with its traceback)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(self.format(record))


@contextmanager
def logged_at_info() -> Iterator[Recorded]:
    """Inside: Prefect's run logs sent to the API and every logger's records from INFO up recorded, as a user's
    default logging shows them (the flow tests otherwise keep both off)."""
    from prefect.settings import PREFECT_LOGGING_TO_API_ENABLED, temporary_settings

    recorded = Recorded()
    loggers = [logging.getLogger(), logging.getLogger("prefect")]
    levels = [logger.level for logger in loggers]
    loggers[0].addHandler(recorded)
    try:
        for logger in loggers:
            logger.setLevel(logging.INFO)
        with temporary_settings(updates={PREFECT_LOGGING_TO_API_ENABLED: True}):
            yield recorded
            APILogHandler().flush()  # the run's logs reach the API in batches
    finally:
        loggers[0].removeHandler(recorded)
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)


@pytest.fixture(scope="module")
def bucket_run(bucket_archive, pixelwise_model: Path, tmp_path_factory) -> tuple[State, Path, list[str]]:
    """The flow run that corrected the bucket's archive into ``s3://bucket/out`` in the flow's process, the
    empty folder it ran in (a URL taken for a local path would write there), and the log lines it recorded."""
    here = tmp_path_factory.mktemp("working-directory")
    with pytest.MonkeyPatch.context() as patch, logged_at_info() as recorded:
        patch.chdir(here)
        state = correct_archive_flow(scans=[bucket_archive], model=str(pixelwise_model), out=OUT, workers=0,
                                     return_state=True)
    return state, here, recorded.lines


def test_correct_archive_flow__bucket_archive_published_in_the_bucket(bucket_archive, bucket_run):
    state, here, _ = bucket_run
    assert state.is_completed(), state.message
    statuses = state.result()["statuses"]
    assert sorted(statuses) == [f"{bucket_archive}{name}.scan.zarr" for name in SCANS]
    assert set(statuses.values()) <= {"corrected", "unchanged"}, statuses
    files = set(bucket_files(OUT))
    for name in SCANS:
        assert f"{name}/{MANIFEST_FILE}" in files
        assert verify_store(f"{OUT}/{name}").kind == "corrected output"
    assert f"summary/{MANIFEST_FILE}" in files and "summary/report.md" in files, "the batch summary is published"
    assert not any(here.iterdir()), "nothing written on the local disk"


def test_correct_archive_flow__no_credential_in_parameters_logs_artifacts_or_outputs(bucket_archive, bucket_run):
    state, _, recorded = bucket_run
    flow_run_id = str(state.state_details.flow_run_id)
    with get_client(sync_client=True) as client:
        parameters = str(client.read_flow_run(UUID(flow_run_id)).parameters)
    assert bucket_archive in parameters and not leaked(parameters)
    logs = wait_for(lambda: flow_run_logs(flow_run_id),
                    lambda found: any("Finished in state" in log.message for log in found))
    assert any("Finished in state" in log.message for log in logs)
    assert not leaked("\n".join(log.message for log in logs))
    assert recorded and not leaked("\n".join(recorded))
    published = flow_run_artifacts(flow_run_id)
    assert SUMMARY_ARTIFACT_KEY in {artifact.key for artifact in published}
    links = sorted(str(artifact.data) for artifact in published if str(artifact.key).startswith("report-"))
    assert links == [f"[report of {name}]({OUT}/{name}/report.html)" for name in SCANS], "reports linked where they lie"
    assert not leaked("\n".join(f"{a.data} {a.description}" for a in published))
    assert not leaked(str(state.message) + str(state.result(raise_on_failure=False)))
    files = bucket_files(OUT)
    assert any(name.endswith(MANIFEST_FILE) for name in files)
    for name, data in files.items():
        assert not leaked(data.decode(errors="replace")), name
