"""The per-store throughput benchmark at its smallest: every store's row, and outputs identical to local disk's."""

from __future__ import annotations

import pytest

from benchmarks.object_stores import STORES, main

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_object_stores_benchmark__small_rows_every_store_and_finds_the_outputs_identical(capsys):
    main(["--small"])
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| ") and not line.startswith("| storage")]
    assert [row.split("|")[1].strip() for row in rows] == [store.name for store in STORES], out
    local = float(rows[0].split("|")[4])
    assert local == 1.0, out
    assert all(float(row.split("|")[3]) > 0 for row in rows), out
    assert "bit-identical to the local disk's (but source and timing fields): yes" in out, out
