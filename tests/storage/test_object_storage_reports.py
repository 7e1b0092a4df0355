"""Report folders in a bucket (`evaluate --out s3://...`, `table2 --out`, the flows' reports): the folder a path
gets, published with its marker last; a report of ours there is replaced, anything else refused whole (moto's S3
server on 127.0.0.1)."""

from __future__ import annotations

import json

import pytest

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.locations import location
from mpi_lidar.reporting.report import REPORT_MARKER, Report, Table, write_report_to
from mpi_lidar.storage import objects
from tests.cli_runner import assert_one_error_line, call_main
from tests.storage.conftest import BUCKET, SECRET

pytestmark = pytest.mark.integration

REPORT_FILES = {"report.md", "report.html", "metrics.json", REPORT_MARKER}


def small_report(value: float) -> Report:
    return Report("a report", [Table(("metric", "value"), (("mae", f"{value:.1f}"),))], data={"mae": value})


def read_json(url: str) -> dict[str, object]:
    text = objects.read_bytes(location(url))
    assert text is not None, url
    return json.loads(text)


def test_write_report_to__bucket_gets_the_folder_a_path_gets_and_a_rerun_replaces_it(s3_server, tmp_path):
    url = f"s3://{BUCKET}/reports/first"
    assert write_report_to(small_report(1.0), url, {}) == url
    assert set(objects.list_files(location(url))) == REPORT_FILES
    write_report_to(small_report(1.0), tmp_path / "here", {})
    assert objects.read_bytes(location(f"{url}/report.md")) == (tmp_path / "here" / "report.md").read_bytes()
    write_report_to(small_report(2.0), url, {})  # our own report there: replaced, as on disk
    assert read_json(f"{url}/metrics.json") == {"mae": 2.0}


def test_write_report_to__prefix_holding_other_objects_is_refused_and_left_as_it_was(s3_server):
    url = f"s3://{BUCKET}/reports/taken"
    objects.write_object(location(f"{url}/notes.txt"), b"someone's notes")
    with pytest.raises(MpiLidarError, match="not a report of ours") as refused:
        write_report_to(small_report(1.0), url, {})
    assert "\n" not in str(refused.value)
    assert objects.list_files(location(url)) == {"notes.txt": len(b"someone's notes")}


def test_evaluate_cli__report_into_bucket(s3_server, pixelwise_model, small_dataset, monkeypatch, capsys):
    url = f"s3://{BUCKET}/reports/evaluation"
    code, stdout, err = call_main(monkeypatch, capsys, "evaluate", "--data", small_dataset, "--model",
                                  pixelwise_model, "--out", url)
    assert code == 0 and f"report written to {url}" in stdout, stdout + err
    assert {"report.md", "metrics.json", REPORT_MARKER} <= set(objects.list_files(location(url)))
    assert read_json(f"{url}/metrics.json")["data"] == str(small_dataset)
    assert SECRET not in stdout + err


def test_evaluate_cli__report_over_foreign_objects_is_one_error_line(s3_server, pixelwise_model, small_dataset,
                                                                     monkeypatch, capsys):
    url = f"s3://{BUCKET}/reports/foreign"
    objects.write_object(location(f"{url}/data.bin"), b"\x00")
    code, _, err = call_main(monkeypatch, capsys, "evaluate", "--data", small_dataset, "--model", pixelwise_model,
                             "--out", url)
    assert code != 0
    assert_one_error_line(err, "not a report of ours")
