"""Draw docs/scan-frame.png: how a scan's azimuth and elevation become x, y, z, and which way rows and columns run.

Run: .venv/bin/python docs/scan_frame.py [--out docs/scan-frame.png]

The rays are computed by the library itself (:func:`mpi_lidar.scans.scan.grid_rays`) on a scan grid ordered as
``mpi-lidar render-scenes`` orders it (row 0 at the top, elevation falling down the rows; azimuth rising along
the columns), so the picture follows the code. x, y, z is a right-handed frame, drawn as such: with +y up and
+z forward, +x is to the left of the scanner.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from mpi_lidar.scans.scan import grid_rays

ROWS, COLUMNS = 5, 7
AZIMUTH_RAD = np.radians(np.linspace(-30, 30, COLUMNS))  # rising along the columns
ELEVATION_RAD = np.radians(np.linspace(20, -20, ROWS))  # falling down the rows: row 0 is the top
RANGE_M = 2.0


def _arrow(ax, start, end, text, colour="black", offset=(0.0, 0.0)) -> None:
    ax.annotate("", xy=end, xytext=start, arrowprops={"arrowstyle": "-|>", "color": colour, "lw": 1.6})
    ax.text(end[0] + offset[0], end[1] + offset[1], text, color=colour, fontsize=10, ha="center", va="center")


def draw(out: Path) -> Path:
    matplotlib.use("Agg")
    rays = grid_rays(AZIMUTH_RAD, ELEVATION_RAD)  # (H, W, 3): x, y, z per pixel
    points = RANGE_M * rays
    fig = Figure(figsize=(13, 4.6), layout="constrained")
    front, top, side = fig.subplots(1, 3)

    # 1. Behind the scanner, looking along +z with +y up: +x is to the left (a right-handed frame), so the page's
    # horizontal axis is -x. The pixel grid is drawn as the points it gives on a sphere of 2 m.
    across, up = -points[..., 0], points[..., 1]
    front.scatter(across, up, s=18, color="0.55")
    front.scatter(across[0, 0], up[0, 0], s=60, color="tab:red", zorder=3)
    front.annotate("row 0, column 0", (across[0, 0], up[0, 0]), (0.25, 0.86), color="tab:red", fontsize=9,
                   arrowprops={"arrowstyle": "-", "color": "tab:red"})
    _arrow(front, (across[0, 0] + 0.12, up[0, 0]), (across[-1, 0] + 0.12, up[-1, 0]),
           "rows\n(elevation\nfalls)", "tab:blue", (0.22, 0.0))
    _arrow(front, (across[-1, 0], up[-1, 0] - 0.12), (across[-1, -1], up[-1, -1] - 0.12),
           "columns (azimuth rises)", "tab:green", (0.45, -0.13))
    _arrow(front, (0, 0), (-0.45, 0), "+x", offset=(-0.08, 0.0))
    _arrow(front, (0, 0), (0, 0.45), "+y", offset=(0.0, 0.07))
    front.text(0.0, -0.07, "+z into the page", fontsize=9, ha="center", va="top")
    front.set_title("behind the scanner, looking along +z")

    # 2. From above (+y towards the reader): azimuth a turns the ray from +z towards +x, counter-clockwise.
    middle = ROWS // 2
    for column in range(COLUMNS):
        top.plot([0, -points[middle, column, 0]], [0, points[middle, column, 2]], color="0.75", lw=0.8)
    top.scatter(-points[middle, :, 0], points[middle, :, 2], s=18, color="tab:green")
    a = AZIMUTH_RAD[-1]
    arc = np.linspace(0, a, 20)
    top.plot(-0.9 * np.sin(arc), 0.9 * np.cos(arc), color="tab:green")
    top.text(-0.95 * np.sin(a / 2) - 0.08, 0.95 * np.cos(a / 2), "a", color="tab:green", fontsize=11)
    top.text(-points[middle, -1, 0], points[middle, -1, 2] + 0.1, f"column {COLUMNS - 1}", fontsize=9,
             ha="center", color="tab:green")
    top.text(-points[middle, 0, 0], points[middle, 0, 2] + 0.1, "column 0", fontsize=9, ha="center",
             color="tab:green")
    _arrow(top, (0, 0), (-0.5, 0), "+x", offset=(-0.09, 0.0))
    _arrow(top, (0, 0), (0, 0.6), "+z", offset=(0.0, 0.07))
    top.text(0.0, -0.08, "+y towards you (up)", fontsize=9, ha="center", va="top")
    top.set_title("from above: x = cos e sin a, z = cos e cos a")

    # 3. From the scanner's right (+x into the page): elevation e turns the ray from +z towards +y.
    centre = COLUMNS // 2
    for row in range(ROWS):
        side.plot([0, points[row, centre, 2]], [0, points[row, centre, 1]], color="0.75", lw=0.8)
    side.scatter(points[:, centre, 2], points[:, centre, 1], s=18, color="tab:blue")
    e = ELEVATION_RAD[0]
    arc = np.linspace(0, e, 20)
    side.plot(0.9 * np.cos(arc), 0.9 * np.sin(arc), color="tab:blue")
    side.text(0.98 * np.cos(e / 2) + 0.05, 0.98 * np.sin(e / 2), "e", color="tab:blue", fontsize=11)
    _arrow(side, (0, 0), (0.6, 0), "+z", offset=(0.09, 0.0))
    _arrow(side, (0, 0), (0, 0.5), "+y", offset=(0.0, 0.07))
    side.text(0.0, -0.08, "+x into the page", fontsize=9, ha="center", va="top")
    side.text(points[0, centre, 2], points[0, centre, 1] + 0.1, "row 0", fontsize=9, ha="center", color="tab:blue")
    side.text(points[-1, centre, 2], points[-1, centre, 1] - 0.1, f"row {ROWS - 1}", fontsize=9, ha="center",
              va="top", color="tab:blue")
    side.set_title("from the side: y = sin e")

    for ax in (front, top, side):
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        for spine in ax.spines.values():
            spine.set_visible(False)
    front.set_xlim(-1.25, 1.55)
    front.set_ylim(-1.0, 1.0)
    top.set_xlim(-1.2, 1.2)
    side.set_xlim(-0.3, 2.2)
    fig.suptitle("The scan frame (right-handed): point = depth x (cos e sin a, sin e, cos e cos a), scanner at the "
                 "origin; row i has elevation_rad[i], column j azimuth_rad[j]", fontsize=11)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "scan-frame.png")
    print(draw(parser.parse_args(argv).out))


if __name__ == "__main__":
    main()
