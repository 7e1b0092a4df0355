"""The one atomic-write helper: its crash-safety contract, tested once for files, directories and links."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.storage.atomic import STAGING_NAME, atomic_path, remove_interrupted_staging, write_text

pytestmark = pytest.mark.unit


def test_atomic_path__publishes_a_file_and_leaves_no_staging(tmp_path):
    target = tmp_path / "a.txt"
    write_text(target, "one")
    write_text(target, "two")
    assert target.read_text() == "two"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_atomic_path__an_exception_leaves_the_old_directory_untouched(tmp_path):
    target = tmp_path / "out"
    with atomic_path(target) as staging:
        staging.mkdir()
        (staging / "x").write_text("old")
    with pytest.raises(RuntimeError), atomic_path(target, replace=True) as staging:
        staging.mkdir()
        (staging / "x").write_text("half")
        raise RuntimeError("killed half-way")
    assert (target / "x").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_atomic_path__replaces_a_directory_whole(tmp_path):
    target = tmp_path / "out"
    for content in ("old", "new"):
        with atomic_path(target, replace=True) as staging:
            staging.mkdir()
            (staging / content).write_text(content)
    assert sorted(p.name for p in target.iterdir()) == ["new"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_atomic_path__refuses_an_existing_target_unless_asked(tmp_path):
    target = tmp_path / "model"
    target.mkdir()
    with pytest.raises(MpiLidarError, match=r"model directory .* already exists"), \
            atomic_path(target, what="model directory"):
        pytest.fail("the block must not run")


def test_atomic_path__keep_refuses_a_foreign_directory(tmp_path):
    target = tmp_path / "report"
    target.mkdir()
    (target / "mine.txt").write_text("user data")
    with pytest.raises(MpiLidarError, match="not an mpi-lidar report"), \
            atomic_path(target, replace=True, what="report", keep=lambda p: True):
        pytest.fail("the block must not run")
    assert (target / "mine.txt").read_text() == "user data"


def test_atomic_path__replaces_a_link_in_one_rename(tmp_path):
    (tmp_path / "v1").mkdir()
    (tmp_path / "v2").mkdir()
    link = tmp_path / "latest"
    for key in ("v1", "v2"):
        with atomic_path(link, replace=True) as staging:
            staging.symlink_to(key, target_is_directory=True)
    assert os.readlink(link) == "v2"


def test_atomic_path__os_errors_become_one_line(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(MpiLidarError, match=r"cannot write scan .*file/x"), \
            atomic_path(blocker / "x", what="scan") as staging:
        staging.write_text("x")


def test_remove_interrupted_staging__a_killed_writer_leaves_only_recognised_debris(tmp_path):
    script = textwrap.dedent(f"""
        import os
        from pathlib import Path
        from mpi_lidar.storage.atomic import atomic_path
        with atomic_path(Path({str(tmp_path)!r}) / "out") as staging:
            staging.mkdir()
            (staging / "part").write_text("half")
            os._exit(9)  # killed: no clean-up runs
    """)
    assert subprocess.run([sys.executable, "-c", script]).returncode == 9
    debris = [p for p in tmp_path.iterdir()]
    assert len(debris) == 1 and STAGING_NAME.match(debris[0].name)
    assert not (tmp_path / "out").exists()
    (tmp_path / "user.txt").write_text("keep")
    assert remove_interrupted_staging(tmp_path) == debris
    assert sorted(p.name for p in tmp_path.iterdir()) == ["user.txt"]
