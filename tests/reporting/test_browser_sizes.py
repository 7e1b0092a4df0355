"""Scan reports of a wide 24 x 96 scan and a 1000 x 1000 one in a real browser at 1280 x 800: nothing overflows
sideways, the maps take the page's width, and the screenshots are taken. The scans are drawn, not corrected: the
layout is what is checked, and a megapixel correction would cost a minute here."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction import Correction, CorrectionOptions, Flag
from mpi_lidar.reporting.scan_outputs import write_scan_outputs
from mpi_lidar.scans.scan import Scan
from tests.reporting.test_browser import WINDOW_PX, browse, chromium  # noqa: F401 - chromium: the fixture

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SCREEN_PX = (WINDOW_PX, 800)


def _drawn_scan(height: int, width: int) -> tuple[Scan, Correction]:
    """A corner's depths on a grid of square pixels (0.6 rad wide), a third of it corrected by 4 mm."""
    azimuth = np.linspace(-0.3, 0.3, width)
    half = 0.3 * height / width
    depth = np.repeat((2.0 - 0.6 * np.abs(np.sin(azimuth)))[None, :], height, axis=0)
    depth = (depth + np.random.default_rng(0).normal(0.0, 0.002, depth.shape)).astype(np.float32)
    frequencies = Config().frequencies_hz
    scan = Scan(name=f"drawn_{height}x{width}", frequencies_hz=frequencies,
                depth=np.repeat(depth[None], len(frequencies), axis=0),
                amplitude=np.full((len(frequencies), height, width), 0.03, np.float32), azimuth_rad=azimuth,
                elevation_rad=np.linspace(half, -half, height))
    corrected = np.repeat((np.abs(azimuth) < 0.1)[None, :], height, axis=0)
    flags = np.where(corrected, int(Flag.CORRECTED), int(Flag.NO_MULTIPATH)).astype(np.uint8)
    return scan, Correction(depth=np.where(corrected, depth - 0.004, depth).astype(np.float32), flags=flags,
                            inference_s=0.0, total_s=0.0)


@pytest.fixture(scope="module")
def scan_reports(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("sizes")
    pages = {}
    for height, width in ((24, 96), (1000, 1000)):
        scan, correction = _drawn_scan(height, width)
        write_scan_outputs(out / scan.name, scan, correction, {}, {"scan_sha256": "0" * 64}, CorrectionOptions(),
                           "full", point_clouds=())
        pages[f"{height}x{width}"] = out / scan.name / "report.html"
    return pages


@pytest.mark.parametrize("size", ["24x96", "1000x1000"])
def test_scan_report__fits_1280_by_800_maps_take_the_page_width(chromium, scan_reports, size, tmp_path):  # noqa: F811
    from PIL import Image

    shot = tmp_path / f"scan-{size}.png"
    findings = browse(chromium, scan_reports[size], screenshot=shot, height_px=SCREEN_PX[1])
    assert findings["problems"] == [] and findings["scrollWidth"] <= WINDOW_PX, findings["scrollWidth"]
    images = {image["src"]: image for image in findings["images"]}
    assert {"maps.png", "point_cloud.png", "thumbnail.png"} <= set(images)
    assert all(image["loaded"] and image["right"] <= findings["width"] + 1 for image in images.values())
    maps = images["maps.png"]
    assert maps["shown"] >= 0.95 * min(findings["content"], maps["natural"]), (maps, findings["content"])
    assert maps["natural"] >= 0.9 * findings["content"], "drawn for the page's width, not scaled up"
    assert findings["plots"] and all(plot["right"] <= findings["width"] + 1 for plot in findings["plots"])
    with Image.open(shot) as image:
        assert image.size == SCREEN_PX
