"""Points and surface normals of a range map along its rays."""

from __future__ import annotations

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
