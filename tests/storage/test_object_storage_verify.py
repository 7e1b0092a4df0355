"""``mpi-lidar verify`` of a damaged dataset in a bucket (moto's S3 server on 127.0.0.1; a whole one is verified
by the how-to's commands, test_object_storage_howto.py), and the one line a store that cannot be reached gives."""

from __future__ import annotations

import socket
import sys
from pathlib import Path

import pytest

from benchmarks.object_storage import OPERATIONS, aws_environment, install_counters, take_counters
from mpi_lidar.config import Config, PriorConfig
from mpi_lidar.errors import MpiLidarError, StoreError
from mpi_lidar.learning.model import load_model
from mpi_lidar.locations import location
from mpi_lidar.storage import objects
from mpi_lidar.workflows.generate import generate
from mpi_lidar.workflows.verify import verify_store
from tests.cli_runner import assert_one_error_line, call_main
from tests.storage.conftest import BUCKET, SECRET

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def local_dataset(tmp_path_factory) -> Path:
    """600 rows of the paper's prior in two chunks, on the local disk."""
    path = tmp_path_factory.mktemp("verify") / "dataset.zarr"
    generate(path, Config(prior=PriorConfig()).replace(dataset={"samples": 600, "chunk_rows": 300, "seed": 7}))
    return path


def upload(local: Path, url: str) -> str:
    objects.filesystem(location(url)).put(str(local) + "/", location(url).path, recursive=True)
    return url


def test_verify__unfinished_or_damaged_dataset_in_bucket_fails(s3_server, local_dataset, monkeypatch, capsys):
    """A dataset whose chunk was never marked done is incomplete; a chunk replaced by another (well-formed,
    but not the rows written there) is found by its fingerprint."""
    url = upload(local_dataset, f"s3://{BUCKET}/verify/damaged.zarr")
    fs, path = objects.filesystem(location(url)), location(url).path
    fs.rm_file(f"{path}/chunk_done/c/1")
    code, stdout, err = call_main(monkeypatch, capsys, "verify", url)
    assert code == 1 and stdout == "", stdout
    assert_one_error_line(err, "incomplete (1 of 2 chunks)")
    fs.pipe_file(f"{path}/chunk_done/c/1", (local_dataset / "chunk_done" / "c" / "1").read_bytes())
    fs.pipe_file(f"{path}/target/c/0", (local_dataset / "target" / "c" / "1").read_bytes())
    with pytest.raises(MpiLidarError, match=r"'target'.*chunk 0|chunk 0.*'target'"):
        verify_store(url)


def test_verify__dataset_in_bucket_read_as_zarr_v3_without_probes(s3_server, local_dataset):
    """The store's schema is read from its ``zarr.json`` alone: one GET where zarr would also probe for Zarr v2
    metadata (three more). Then one HEAD (is it a published output folder? no manifest),
    two listings (that HEAD's, and the store's for its checks) and the dataset's pass: each of the six arrays'
    metadata and the root's once, and each chunk's six objects."""
    url = upload(local_dataset, f"s3://{BUCKET}/verify/counted.zarr")
    install_counters()
    take_counters()
    assert verify_store(url).chunks == 2
    asked = {name: int(n) for name, n in take_counters().items() if name in OPERATIONS}
    assert asked == {"HeadObject": 1, "ListObjectsV2": 2, "GetObject": 1 + (1 + 6) + 6 * 2}, asked


def test_verify__foreign_zarr_v2_store_in_bucket_named_by_its_schema(s3_server):
    """Another tool's Zarr v2 group (no ``zarr.json``) is still opened and said to be no store of ours."""
    import zarr

    url = f"s3://{BUCKET}/verify/foreign-v2.zarr"
    group = zarr.open_group(store=objects.zarr_store(location(url), read_only=False), mode="w", zarr_format=2)
    group.attrs["title"] = "another tool's"
    with pytest.raises(StoreError, match=r"not an mpi-lidar dataset, scan or published corrected output "
                                         r"\(schema None\)"):
        verify_store(url)


@pytest.mark.parametrize(("url", "modules"), [("gs://bucket/scans/a.scan.zarr", ("gcsfs", "gcsfs.core")),
                                              ("az://container/scans/a.scan.zarr", ("adlfs",))])
def test_store_without_its_library__one_line_names_the_package(url, modules, monkeypatch, capsys):
    """gcsfs and adlfs come with the tool; in an install without one (here its import blocked, and fsspec's
    registry of the classes it imported already forgotten) reading or writing gs:// or az:// says which package
    to install, in one line."""
    import importlib

    library = modules[0]
    for name in modules:
        monkeypatch.setitem(sys.modules, name, None)
    registry = importlib.import_module("fsspec.registry")._registry  # fsspec.registry is its read-only view
    monkeypatch.delitem(registry, location(url).scheme, raising=False)
    assert objects.STORE_LIBRARIES[location(url).scheme] == library
    for command in (("verify", url), ("correct", url, "--model", "model", "--out", "out")):
        code, stdout, err = call_main(monkeypatch, capsys, *command)
        assert code in (1, 2) and stdout == "", stdout
        assert_one_error_line(err, f"the {library} package, which is not installed; install it (pip install {library}")
        assert "not supported" not in err
    with pytest.raises(MpiLidarError, match=f"{library} package"):
        load_model(url.replace("scans/a.scan.zarr", "model"))


def test_unreachable_s3_endpoint__one_line_names_what_to_check(moto_endpoint, monkeypatch, capsys):
    """A server that does not answer (a closed port): one line naming the location and the endpoint variable,
    never the secret; botocore's retries are cut to one attempt to keep the test short."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        closed = probe.getsockname()[1]
    monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")
    with aws_environment(f"http://127.0.0.1:{closed}", "AKIAMPILIDARTEST", SECRET):
        code, stdout, err = call_main(monkeypatch, capsys, "verify", f"s3://{BUCKET}/d.zarr")
        with pytest.raises(StoreError, match=f"cannot read s3://{BUCKET}/model/card.json .*AWS_ENDPOINT_URL"):
            load_model(f"s3://{BUCKET}/model")
    assert code == 1 and stdout == ""
    assert_one_error_line(err, f"s3://{BUCKET}/d.zarr")
    assert "AWS_ENDPOINT_URL" in err and SECRET not in err
