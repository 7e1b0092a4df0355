"""The object-storage benchmark at its small size: its table, and outputs from the bucket bit-identical to disk's."""

from __future__ import annotations

import pytest

from benchmarks.object_storage import main

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_object_storage_benchmark__small_run_prints_both_storages_and_identical_outputs(tmp_path, capsys):
    main(["--small", "--work", str(tmp_path)])  # fails (SystemExit) where an output differs but for provenance
    printed = capsys.readouterr().out
    rows = {line.split("|")[1].strip(): line.split("|") for line in printed.splitlines() if line.startswith("| ")}
    assert {"local disk", "S3"} <= set(rows)
    assert float(rows["S3"][10]) > 0 and float(rows["S3"][11]) > 0  # GET and PUT requests per scan counted
    assert "bit-identical to the local disk's (but source and timing fields): yes" in printed
