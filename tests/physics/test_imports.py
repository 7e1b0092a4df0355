"""Physics stands on the foundation only; the configuration imports nothing of the physics."""

from __future__ import annotations

import grimp
import pytest

pytestmark = pytest.mark.unit

FOUNDATION = {"mpi_lidar.constants", "mpi_lidar.errors", "mpi_lidar.timing", "mpi_lidar.config"}


def _imports_of(graph: grimp.ImportGraph, package: str) -> set[str]:
    modules = {m for m in graph.modules if m == package or m.startswith(package + ".")}
    imported = set().union(*(graph.find_modules_directly_imported_by(m) for m in modules))
    return {m for m in imported if m.startswith("mpi_lidar")} - modules


def test_physics__imports_only_the_foundation():
    graph = grimp.build_graph("mpi_lidar", cache_dir=None)
    assert _imports_of(graph, "mpi_lidar.physics") <= FOUNDATION


def test_foundation__imports_nothing_of_the_physics():
    graph = grimp.build_graph("mpi_lidar", cache_dir=None)
    for module in FOUNDATION:
        assert not {m for m in _imports_of(graph, module) if m.startswith("mpi_lidar.physics")}, module
