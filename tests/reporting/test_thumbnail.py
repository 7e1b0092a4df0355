"""The thumbnail of the default output level: its image, its colours and its PNG, drawn without matplotlib."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.correction import Correction, Flag
from mpi_lidar.reporting.thumbnail import FLAG_COLOURS, THUMBNAIL_PX, thumbnail_image, viridis, write_png

pytestmark = pytest.mark.unit


def test_thumbnail_image__at_most_512_pixels_depth_left_flags_right():
    flags = np.full((1500, 3000), Flag.NO_MULTIPATH, dtype=np.uint8)
    flags[:, :1500] = Flag.CORRECTED
    depth = np.tile(np.linspace(1.0, 3.0, 3000, dtype=np.float32), (1500, 1))
    depth[0, 0] = np.nan
    big, (low, high) = thumbnail_image(Correction(depth=depth, flags=flags))
    assert max(big.shape[:2]) <= THUMBNAIL_PX and big.dtype == np.uint8 and big.shape[2] == 3
    assert 1.0 <= low < high <= 3.0
    half = big.shape[1] // 2 + 2
    assert tuple(big[10, half + 2]) == tuple(int(FLAG_COLOURS[Flag.CORRECTED][i:i + 2], 16) for i in (1, 3, 5))
    assert tuple(big[10, -2]) == tuple(int(FLAG_COLOURS[Flag.NO_MULTIPATH][i:i + 2], 16) for i in (1, 3, 5))
    assert tuple(big[0, 0]) == (255, 255, 255), "invalid pixels are white"


def test_viridis__the_bytes_matplotlib_gives_for_the_same_values():
    from matplotlib import colormaps

    values = np.concatenate([np.random.default_rng(0).random(5000), [0.0, 1.0, 0.5, 255.5 / 256, 1 / 256]])
    assert np.array_equal(viridis(values), colormaps["viridis"](values, bytes=True)[..., :3])


def test_write_png__matplotlib_reads_back_the_same_pixels(tmp_path):
    from matplotlib.image import imread

    image = np.random.default_rng(1).integers(0, 256, size=(37, 53, 3), dtype=np.uint8)
    write_png(tmp_path / "t.png", image)
    back = imread(tmp_path / "t.png")
    assert back.shape == image.shape
    assert np.array_equal(np.round(back * 255).astype(np.uint8), image)


def test_thumbnail_image__a_small_scan_zoomed_a_mirrored_one_right_to_left():
    flags = np.full((24, 96), Flag.NO_MULTIPATH, dtype=np.uint8)
    flags[:, :10] = Flag.CORRECTED  # the first columns: the scanner's right where azimuth grows along them
    depth = np.tile(np.linspace(1.0, 3.0, 96, dtype=np.float32), (24, 1))
    plain, _ = thumbnail_image(Correction(depth=depth, flags=flags))
    assert plain.shape == (2 * 24, 2 * (2 * 96) + 4, 3)  # 2 x: each panel at most (512 - 4) / 2 pixels wide
    mirrored, _ = thumbnail_image(Correction(depth=depth, flags=flags), mirror=True)
    assert np.array_equal(mirrored[:, :192], plain[:, 191::-1])  # each panel's columns right to left
    assert np.array_equal(mirrored[:, -192:], plain[:, :-193:-1])
    corrected = tuple(int(FLAG_COLOURS[Flag.CORRECTED][i:i + 2], 16) for i in (1, 3, 5))
    assert tuple(mirrored[0, -1]) == corrected and tuple(plain[0, -1]) != corrected
