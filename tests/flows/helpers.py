"""Small helpers of the flow tests: a config file, and reads of what a flow run left in the Prefect API."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar
from uuid import UUID

from prefect import get_client
from prefect.client.schemas.filters import (
    ArtifactFilter,
    ArtifactFilterFlowRunId,
    ArtifactFilterKey,
    FlowRunFilter,
    FlowRunFilterId,
    FlowRunFilterParentFlowRunId,
    TaskRunFilter,
    TaskRunFilterName,
)
from prefect.client.schemas.objects import Artifact, FlowRun, TaskRun

SAMPLES = 2000
CHUNK_ROWS = 500
CHUNKS = SAMPLES // CHUNK_ROWS
SEED = 20260101

T = TypeVar("T")


def write_config(path: Path, seed: int = SEED) -> Path:
    """A TOML file for a 4-chunk dataset of two thousand rows."""
    path.write_text(f"[dataset]\nsamples = {SAMPLES}\nchunk_rows = {CHUNK_ROWS}\nseed = {seed}\n")
    return path


def wait_for(read: Callable[[], list[T]], ready: Callable[[list[T]], bool], timeout_s: float = 30.0) -> list[T]:
    """Poll ``read`` until ``ready`` holds: task runs reach the API as events, a moment after they ran."""
    deadline = time.monotonic() + timeout_s
    found = read()
    while not ready(found) and time.monotonic() < deadline:
        time.sleep(0.5)
        found = read()
    return found


def chunk_task_runs(flow_run_id: str) -> list[TaskRun]:
    """The write-chunk task runs the API recorded for one flow run."""
    with get_client(sync_client=True) as client:
        return client.read_task_runs(
            flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[UUID(flow_run_id)])),
            task_run_filter=TaskRunFilter(name=TaskRunFilterName(like_="write-chunk")),
        )


def subflow_runs(flow_run_id: str) -> list[FlowRun]:
    with get_client(sync_client=True) as client:
        return client.read_flow_runs(
            flow_run_filter=FlowRunFilter(parent_flow_run_id=FlowRunFilterParentFlowRunId(any_=[UUID(flow_run_id)]))
        )


def artifacts(flow_run_id: str, key: str) -> list[Artifact]:
    with get_client(sync_client=True) as client:
        return client.read_artifacts(
            artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=[key]),
                                           flow_run_id=ArtifactFilterFlowRunId(any_=[UUID(flow_run_id)]))
        )
