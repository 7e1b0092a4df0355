"""The mixed-pixel stage's one-sided test: a pixel beside a surface with no usable return is mixed where its footprint
lost the lit side's light and its depth lies off the lit side's; a silhouette pixel whose depth stays on its surface,
a pixel with its full light, and a grazing lit side are not."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.correction._mixed_dark import DARK_REACH, MIN_EDGE_M, beside_no_return, lost_light

pytestmark = pytest.mark.unit

H, W = 16, 14
INNER = slice(DARK_REACH, H - DARK_REACH)  # rows whose blocks lie inside the scene
EDGE = 6  # the column between the dark side (left) and the lit side (right)
SIGMA_M = 0.01  # a lit pixel's noise [m]
LIGHT_V2 = 1e-3  # a lit pixel's summed amplitude [V^2]


def _scene(edge_depth_m: float, edge_light: float, slope_m: float = 0.0):
    """A lit wall at 10 m right of ``EDGE`` (depth rising ``slope_m`` per pixel), no return left of it, and the edge
    column at ``edge_depth_m`` with ``edge_light`` of a lit pixel's amplitude; noiseless values, exact noise."""
    columns = 10.0 + slope_m * (np.arange(W) - EDGE)
    depth = np.tile(columns, (H, 1)).astype(np.float32)
    depth[:, EDGE] = edge_depth_m
    amplitude = np.full((H, W), LIGHT_V2)
    amplitude[:, EDGE] *= edge_light
    amplitude[:, :EDGE] = 0.02 * LIGHT_V2
    sigma = np.full((H, W), SIGMA_M, np.float32)
    no_return = np.zeros((H, W), bool)
    no_return[:, :EDGE] = True
    return depth, sigma, amplitude, np.full((H, W), 0.01 * LIGHT_V2), no_return


def _found(depth, sigma, amplitude, amplitude_sigma, no_return):
    where = beside_no_return(no_return) & ~no_return
    return lost_light(depth, sigma, amplitude, amplitude_sigma, no_return, where)


def test_beside_no_return__the_eight_neighbours_of_a_dark_pixel():
    dark = np.zeros((5, 5), bool)
    dark[2, 2] = True
    found = beside_no_return(dark)
    assert found.sum() == 8 and found[1:4, 1:4].sum() == 8 and not found[2, 2]


@pytest.mark.parametrize("offset_m", [-0.08, 0.08])
def test_lost_light__a_pixel_that_lost_half_the_light_and_lies_off_the_lit_side(offset_m):
    """Half the light lost to the dark side, the depth 8 cm off either way: the whole edge column, nothing else."""
    found = _found(*_scene(10.0 + offset_m, 0.5))
    assert found[:, EDGE].all() and found.sum() == H


def test_lost_light__a_silhouette_pixel_on_its_surface_or_with_its_full_light_is_left():
    """A depth 2 cm off (under MIN_EDGE_M less the level's noise), or 8 cm off with all its light: no loss of light to
    a second surface shows."""
    assert MIN_EDGE_M - SIGMA_M > 0.02
    assert not _found(*_scene(10.02, 0.5)).any()
    assert not _found(*_scene(10.08, 0.95)).any()


def test_lost_light__a_grazing_lit_side_is_carried_back_to_the_pixel():
    """The lit side rises 2.5 cm per pixel: its blocks' line carried back to the edge column gives its depth there
    (the first block's level alone lies 3.75 cm further), so an edge pixel on that line is left and one 7 cm beyond
    it, 3.25 cm from the first block's level, is found (rows whose blocks lie inside the scene)."""
    assert not _found(*_scene(10.0, 0.5, slope_m=0.025))[INNER].any()
    assert _found(*_scene(10.07, 0.5, slope_m=0.025))[INNER, EDGE].all()
