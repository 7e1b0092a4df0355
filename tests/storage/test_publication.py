"""The guarantees every :class:`OutputLock` states, one test class run against each implementation (the local
directory's flock so far); other processes holding the lock: tests/workflows/test_output_lock.py."""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path, PurePosixPath

import pytest

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.storage.atomic import atomic_path
from mpi_lidar.storage.publication import LocalOutputLock, OutputLock

pytestmark = pytest.mark.unit

LOCKS: dict[str, Callable[[Path], OutputLock]] = {"local": LocalOutputLock}


@pytest.fixture(params=sorted(LOCKS))
def make_lock(request) -> Callable[[Path], OutputLock]:
    return LOCKS[request.param]


def _refused_in_another_thread(lock: OutputLock) -> list[str]:
    refused: list[str] = []

    def second() -> None:
        try:
            with lock.hold():
                pass
        except MpiLidarError as exc:
            refused.append(str(exc))

    thread = threading.Thread(target=second)
    thread.start()
    thread.join()
    return refused


class TestOutputLock:
    def test_hold__a_second_holder_is_refused_with_one_line(self, make_lock, tmp_path):
        with make_lock(tmp_path).hold():
            [line] = _refused_in_another_thread(make_lock(tmp_path))
        assert "\n" not in line and "being written by another" in line

    def test_hold__free_again_when_the_block_ends(self, make_lock, tmp_path):
        with make_lock(tmp_path).hold():
            pass
        assert _refused_in_another_thread(make_lock(tmp_path)) == []

    def test_hold__free_again_when_the_block_raises(self, make_lock, tmp_path):
        with pytest.raises(RuntimeError), make_lock(tmp_path).hold():
            raise RuntimeError("the batch failed")
        assert _refused_in_another_thread(make_lock(tmp_path)) == []

    def test_hold__nested_in_one_thread_is_one_hold(self, make_lock, tmp_path):
        lock = make_lock(tmp_path)
        with lock.hold():
            with make_lock(tmp_path).hold():
                pass
            assert len(_refused_in_another_thread(lock)) == 1, "the outer hold still holds"
        assert _refused_in_another_thread(lock) == []

    def test_remove_interrupted__removes_staging_and_keeps_outputs(self, make_lock, tmp_path):
        (tmp_path / "day1" / "frame").mkdir(parents=True)
        (tmp_path / "day1" / ".frame.writing-0123abcd").mkdir()
        with pytest.raises(RuntimeError), atomic_path(tmp_path / "day1" / "other"):
            raise RuntimeError("never published")
        lock = make_lock(tmp_path)
        with lock.hold():
            lock.remove_interrupted(PurePosixPath("day1"))
        assert sorted(p.name for p in (tmp_path / "day1").iterdir()) == ["frame"]
