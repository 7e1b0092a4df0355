"""What a scan's facing block pairs say of its surfaces: which surfaces meet and which face each other
(:func:`distinct_pairs` of the pairs' labels), and the pairs the partner planes do not describe."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.scans.geometry import FacingBlocks


@dataclass(frozen=True)
class BlockPairs:
    """Facing block pairs: receiving block A and partner block B (flat block indices), the coupling kappa_B at
    A_fp = 1 m^2 [1] and the distance A-B [m], each (n,)."""

    receiver: NDArray[np.intp]
    partner: NDArray[np.intp]
    kappa: NDArray[np.float64]
    distance_m: NDArray[np.float64]

    @property
    def size(self) -> int:
        return int(self.receiver.size)


def block_pairs_off_planes(blocks: FacingBlocks, components: NDArray, labels: NDArray, narrow: set[int],
                           planes: set[int], patched: set[int]) -> tuple[BlockPairs, BlockPairs]:
    """The block pairs the planes do not describe: those of a
    receiver A on a plane whose partner B is neither a patched plane nor a narrow strip (a curved partner),
    and all those of a receiver on no plane."""
    a, b = blocks.index[blocks.pairs.a], blocks.index[blocks.pairs.b]
    kappa, distance = blocks.pairs.kappa(1.0), blocks.pairs.distance_m
    on_plane = np.isin(labels[a], sorted(planes))
    curved = on_plane & ~np.isin(components[b], sorted(patched | narrow))
    return (BlockPairs(a[curved], b[curved], kappa[curved], distance[curved]),
            BlockPairs(a[~on_plane], b[~on_plane], kappa[~on_plane], distance[~on_plane]))


def meeting_surfaces(blocks: FacingBlocks, components: NDArray, planes: set[int]) -> dict[int, set[int]]:
    """Per modelled surface (label in ``planes``), the other modelled surfaces it meets: those with which its blocks
    have facing pairs."""
    facing = distinct_pairs(components[blocks.index[blocks.pairs.a]], components[blocks.index[blocks.pairs.b]])
    found: dict[int, set[int]] = {}
    for one, other in facing | {(other, one) for one, other in facing}:
        if one != other and one in planes and other in planes:
            found.setdefault(one, set()).add(other)
    return found


def distinct_pairs(first: NDArray, second: NDArray) -> set[tuple[int, int]]:
    """The distinct pairs (first[i], second[i]) of two label arrays (n,) whose labels are -1 or more.

    Each pair is one integer, so one sort of n numbers finds them: ``np.unique(..., axis=0)`` of the (n, 2)
    rows sorts them as records, some 20x slower on a scan's tens of thousands of facing block pairs."""
    if first.size == 0:
        return set()
    base = int(max(first.max(), second.max())) + 2
    codes = np.unique((first.astype(np.int64) + 1) * base + (second.astype(np.int64) + 1))
    return {(int(one) - 1, int(other) - 1) for one, other in zip(*np.divmod(codes, base), strict=True)}


def surfaces_facing(blocks: FacingBlocks, labels: NDArray, components: NDArray, planes: set[int],
                    patched: set[int]) -> dict[int, set[int]]:
    """Per modelled surface (label in ``planes``), the patched planes it receives light from: those its blocks
    have facing pairs with."""
    a, b = blocks.index[blocks.pairs.a], blocks.index[blocks.pairs.b]
    receiving = distinct_pairs(labels[a], components[b])
    return {own: {other for one, other in receiving if one == own} & patched - {own} for own in planes}
