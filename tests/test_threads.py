"""Work on every core: results in order, and the error of the first item that fails."""

from __future__ import annotations

import threading
import time

import pytest

from mpi_lidar.threads import cores, on_cores

pytestmark = pytest.mark.unit


@pytest.fixture
def four_cores(monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 4)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)


def test_cores__one_per_core_unless_omp_num_threads_asks_for_fewer(four_cores, monkeypatch):
    assert cores() == 4
    for budget, expected in (("1", 1), ("3", 3), ("16", 4), ("0", 1), ("many", 4), ("", 4)):
        monkeypatch.setenv("OMP_NUM_THREADS", budget)
        assert cores() == expected, budget


def test_on_cores__a_dask_worker_budget_of_one_thread_runs_here(four_cores, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # as Dask sets it in its worker processes
    assert on_cores(lambda _: threading.get_ident(), range(5)) == [threading.get_ident()] * 5


def test_on_cores__results_come_in_the_items_order_from_several_threads(four_cores):
    seen: set[int] = set()

    def slow_square(item: int) -> int:
        time.sleep(0.002 * (20 - item))  # later items finish first
        seen.add(threading.get_ident())
        return item * item

    assert on_cores(slow_square, range(20)) == [k * k for k in range(20)]
    assert len(seen) > 1


def test_on_cores__the_first_failing_item_in_order_raises(four_cores):

    def check(item: int) -> int:
        time.sleep(0.001 * (10 - item))
        if item in (3, 7):
            raise ValueError(f"item {item}")
        return item

    with pytest.raises(ValueError, match="item 3"):
        on_cores(check, range(10))


def test_on_cores__one_core_or_one_item_runs_in_this_thread(monkeypatch):
    here = threading.get_ident()
    assert on_cores(lambda _: threading.get_ident(), [0]) == [here]
    monkeypatch.setattr("os.cpu_count", lambda: 1)
    assert on_cores(lambda _: threading.get_ident(), range(5)) == [here] * 5
    assert on_cores(lambda item: item, []) == []
