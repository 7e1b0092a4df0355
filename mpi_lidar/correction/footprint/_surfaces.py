"""The scan's surfaces: connected blocks whose planes agree, and the flat ones among them.

Two neighbouring blocks of :class:`mpi_lidar.scans.geometry.FacingBlocks` belong to one surface when their
normals agree and each centre lies on the other's plane (F1); a depth step is another surface. A surface is
flat without its blocks that bend away from its mean normal (F2), and with enough blocks left.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.scans.geometry import FacingBlocks

# A surface is a connected set of blocks whose normals agree to this [deg] and whose centres lie on each
# other's planes (a depth step is another surface) ...
NEIGHBOUR_ANGLE_DEG = 20.0
# ... and whose blocks bend from the surface's mean normal by less than this [deg]; bending blocks are left out.
SURFACE_ANGLE_DEG = 25.0
MIN_SURFACE_BLOCKS = 3
# Share of a surface's members (its blocks, or the fit's pixels), those with the least predicted coupling, that
# stand for it away from its partners: its albedo and its plane's anchors.
ANCHOR_SHARE = 0.4


class SurfaceLabels(NamedTuple):
    """Two labellings of the blocks (Hb*Wb,), -1 where none.

    Attributes
    ----------
    components : NDArray[np.intp]
        The connected surface of every usable block (F1).
    flat : NDArray[np.intp]
        The flat surfaces among them: without the blocks that bend away (F2) and without surfaces of fewer
        than ``MIN_SURFACE_BLOCKS`` blocks.
    """

    components: NDArray[np.intp]
    flat: NDArray[np.intp]


def surface_labels(blocks: FacingBlocks) -> SurfaceLabels:
    """Connected surfaces of the blocks, and the flat surfaces among them.

    Neighbouring blocks a, b join when their normals agree and each centre lies on the other's plane:

    (F1)  n_a . n_b > cos(NEIGHBOUR_ANGLE_DEG),  |n_a . (c_b - c_a)|, |n_b . (c_b - c_a)| <= 3 (rms_a + rms_b)
          + 0.2 |c_b - c_a|

    Within a surface of mean normal n_s, a block bends away where

    (F2)  n . n_s < cos(SURFACE_ANGLE_DEG),

    and surfaces of fewer than ``MIN_SURFACE_BLOCKS`` blocks are dropped.

    Parameters
    ----------
    blocks : FacingBlocks
        The scan's blocks (:func:`mpi_lidar.scans.geometry.facing_blocks`).

    Returns
    -------
    SurfaceLabels
        The connected and the flat surface of every block.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    hb, wb = blocks.usable.shape
    flat = np.arange(hb * wb).reshape(hb, wb)
    normals, centres = blocks.normals.reshape(-1, 3), blocks.centres.reshape(-1, 3)
    usable, rms = blocks.usable.ravel(), blocks.rms_m.ravel()
    edges = []
    for a, b in ((flat[:, :-1], flat[:, 1:]), (flat[:-1, :], flat[1:, :])):
        a, b = a.ravel(), b.ravel()
        offset = centres[b] - centres[a]
        gap = np.linalg.norm(offset, axis=1)
        tolerance = 3 * (rms[a] + rms[b]) + 0.2 * gap
        agree = (usable[a] & usable[b]
                 & (np.einsum("ij,ij->i", normals[a], normals[b]) > np.cos(np.deg2rad(NEIGHBOUR_ANGLE_DEG)))
                 & (np.abs(np.einsum("ij,ij->i", normals[a], offset)) <= tolerance)
                 & (np.abs(np.einsum("ij,ij->i", normals[b], offset)) <= tolerance))
        edges.append((a[agree], b[agree]))
    rows = np.concatenate([e[0] for e in edges])
    cols = np.concatenate([e[1] for e in edges])
    graph = coo_matrix((np.ones(rows.size), (rows, cols)), shape=(hb * wb, hb * wb))
    _, labels = connected_components(graph, directed=False)
    labels = np.where(usable, labels, -1)
    components = labels.copy()
    # Mean normal per surface; blocks bending away from it are left out, then small surfaces.
    valid = labels >= 0
    sums = np.zeros((labels.max() + 2, 3))
    np.add.at(sums, labels[valid], normals[valid])
    mean = sums / np.maximum(np.linalg.norm(sums, axis=1, keepdims=True), 1e-12)
    bends = np.einsum("ij,ij->i", normals, mean[labels]) < np.cos(np.deg2rad(SURFACE_ANGLE_DEG))
    labels = np.where(valid & ~bends, labels, -1)
    counts = np.bincount(labels[labels >= 0], minlength=labels.max() + 2)
    return SurfaceLabels(components, np.where((labels >= 0) & (counts[labels] >= MIN_SURFACE_BLOCKS), labels, -1))


def pair_coupling(blocks: FacingBlocks) -> NDArray[np.float64]:
    """The white coupling at unit footprint (A_fp = 1 m^2) per block (Hb*Wb,) from its facing block pairs: the sum
    of kappa_B over the blocks B it faces. [1]

    Zero for a block that faces nothing; the blocks next to an edge have no pairs (too close for one).
    """
    return np.asarray(np.bincount(blocks.index[blocks.pairs.a], blocks.pairs.kappa(1.0), minlength=blocks.usable.size),
                      dtype=np.float64)
