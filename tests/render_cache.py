"""Renders that share their light transport: it draws nothing (the sensor model draws the noise), so renders of one
scene that differ in the seed or the noise alone are the same scans, bit for bit, from one transport."""

from __future__ import annotations

from collections.abc import Hashable, Iterator
from contextlib import contextmanager
from unittest import mock

from mpi_lidar.simulation.scenes import _render

_TRANSPORTS: dict[Hashable, tuple] = {}


@contextmanager
def transport_shared_as(key: Hashable) -> Iterator[None]:
    """Within it, the renderer's light transport is worked out once for ``key`` (what sets it: the scene, the
    footprint, the patch spacing) and its arrays are read-only."""
    transport = _render.light_transport

    def shared(*args, **kwargs):
        if key not in _TRANSPORTS:
            arrays = transport(*args, **kwargs)
            for array in arrays:
                array.flags.writeable = False
            _TRANSPORTS[key] = arrays
        return _TRANSPORTS[key]

    with mock.patch.object(_render, "light_transport", shared):
        yield
