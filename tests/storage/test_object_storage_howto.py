"""The commands of docs/how-to/object-storage.md's "Models in a bucket" run as written (small sizes), against
moto's S3 server on 127.0.0.1, in a bucket of their own."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from mpi_lidar.config import Config, PriorConfig
from mpi_lidar.locations import location
from mpi_lidar.scans.store import write_scan
from mpi_lidar.storage import objects
from mpi_lidar.workflows.generate import generate
from tests.cli_runner import call_main
from tests.scan_factory import two_path_scan
from tests.storage.conftest import SECRET

pytestmark = pytest.mark.integration

HOW_TO = Path(__file__).resolve().parents[2] / "docs" / "how-to" / "object-storage.md"
BUCKET = "howto"
# Appended to `train` to keep it short: a handful of shallow trees, trained in this process.
SMALL_TRAINING = ("--params", "params.json", "--workers", "0")


def models_block() -> list[str]:
    """The command lines of the page's "Models in a bucket" block."""
    section = HOW_TO.read_text().split("\n## Models in a bucket\n", 1)[1].split("\n## ", 1)[0]
    block = re.findall(r"```bash\n(.*?)```", section, flags=re.S)[0]
    return [line for line in block.splitlines() if line.strip()]


def test_how_to_models_block__runs_as_written(s3_server, tmp_path, monkeypatch, capsys, caplog):
    """runs/d.zarr is a 600-row dataset on disk and in the bucket (datasets/d.zarr), scans/ holds one scan."""
    monkeypatch.chdir(tmp_path)
    generate(Path("runs/d.zarr"), Config(prior=PriorConfig()).replace(
        dataset={"samples": 600, "chunk_rows": 300, "seed": 9}))
    write_scan(two_path_scan("frame1", seed=1), Path("scans/frame1.scan.zarr"))
    Path("params.json").write_text('{"max_depth": 2, "learning_rate": 0.9}')
    fs = objects.filesystem(location(f"s3://{BUCKET}"))
    fs.mkdir(BUCKET)
    fs.put("runs/d.zarr/", f"{BUCKET}/datasets/d.zarr", recursive=True)
    expected = {"train": f"model written to s3://{BUCKET}/models/m: ", "correct": "1 scan in ",
                "verify": f"ok s3://{BUCKET}/datasets/d.zarr: dataset, 2 chunks"}
    lines = models_block()
    assert [shlex.split(line)[1] for line in lines] == list(expected)
    for line in lines:
        words = [word.replace("s3://bucket/", f"s3://{BUCKET}/") for word in shlex.split(line)[1:]]
        words += list(SMALL_TRAINING) if words[0] == "train" else []
        code, stdout, err = call_main(monkeypatch, capsys, *words)
        assert code == 0 and expected[words[0]] in stdout, f"{line}: exit {code}\n{stdout}{err}"
        assert SECRET not in stdout + err
        if words[0] == "train":  # a second training there is refused before it trains
            code, stdout, err = call_main(monkeypatch, capsys, *words)
            assert code == 2 and f"model directory s3://{BUCKET}/models/m already exists" in err, err
            assert "training" not in stdout + err
    card = fs.cat_file(f"{BUCKET}/models/m/card.json").decode()
    assert '"path": "runs/d.zarr"' in card and SECRET not in card + caplog.text
