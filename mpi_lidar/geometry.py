"""Geometry from a scan: point clouds, surface normals, PLY export."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray


def point_cloud(depth: NDArray, rays: NDArray) -> NDArray[np.float64]:
    """Points (H, W, 3) [m] of a range map (H, W) [m] along unit rays (H, W, 3)."""
    return np.asarray(depth, dtype=np.float64)[..., None] * np.asarray(rays, dtype=np.float64)


def surface_normals(points: NDArray) -> NDArray[np.float64]:
    """Unit normals (H, W, 3) from central differences of the point grid, oriented towards the scanner.

    Pixels whose neighbourhood holds a non-finite point get NaN normals.
    """
    p = np.asarray(points, dtype=np.float64)
    du = np.gradient(p, axis=1)
    dv = np.gradient(p, axis=0)
    n = np.cross(du, dv)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.divide(n, length, out=np.full_like(n, np.nan), where=length > 0)
    facing_away = np.einsum("hwk,hwk->hw", n, p) > 0
    n[facing_away] *= -1
    return n


def write_ply(path: str | Path, points: NDArray, values: NDArray | None = None) -> Path:
    """Write finite points (N, 3) [m] as a binary little-endian PLY, with an optional scalar per point.

    Written through a temporary file and a rename, so a reader never sees half a file.
    """
    path = Path(path)
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    keep = np.isfinite(pts).all(axis=1)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if values is not None:
        fields.append(("value", "<f4"))
    records = np.empty(int(keep.sum()), dtype=fields)
    for axis, name in enumerate("xyz"):
        records[name] = pts[keep, axis]
    if values is not None:
        records["value"] = np.asarray(values, dtype=np.float32).reshape(-1)[keep]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {records.size}"]
    header += [f"property float {name}" for name, _ in fields] + ["end_header", ""]
    staging = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with staging.open("wb") as handle:
        handle.write("\n".join(header).encode("ascii"))
        handle.write(records.tobytes())
    os.replace(staging, path)
    return path


def read_ply_points(path: str | Path) -> NDArray[np.float32]:
    """Points (N, 3) of a PLY written by :func:`write_ply` (for checks and round trips)."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    count = int(next(line.split()[-1] for line in header if line.startswith("element vertex")))
    properties = [line.split()[-1] for line in header if line.startswith("property float")]
    records = np.frombuffer(data[end:], dtype=[(name, "<f4") for name in properties], count=count)
    return np.stack([records["x"], records["y"], records["z"]], axis=1)
