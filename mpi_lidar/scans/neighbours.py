"""Neighbours in numpy alone: the pairs of points within a radius, the nearest point of a set, and bilinear
interpolation on a grid.

scipy has all three (``cKDTree.query_pairs``, ``cKDTree.query``, ``ndimage.map_coordinates`` at order 1 with mode
"nearest"), but importing scipy.spatial and scipy.ndimage costs a one-scan correction about 0.1 s of start-up,
more than these searches take on a scan's few hundred blocks. The results are theirs: the same pairs, the same
nearest distances, and interpolated values equal to the last bit.

The pair search sorts the points into a uniform grid of cubic cells one radius wide: a point's partners lie in its
own cell or in the cells around it. The nearest-point search compares every position with every point where the
set is small, and otherwise descends a tree of cells halved level by level, keeping the cells that may hold a
point as near as the best found so far.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import numpy as np
from numpy.typing import NDArray

# Candidate pairs whose distances are worked out at once: their temporaries take about 60 bytes each.
CANDIDATES_PER_CHUNK = 2**18
# Below this many position-point pairs a nearest-point search compares every position with every point: cheaper
# than a tree of cells for the few hundred blocks of a scan.
BRUTE_FORCE_PAIRS = 2**20
# A search compares the points of a cell holding at most this many directly, without dividing it further.
LEAF_POINTS = 16
# Grid positions interpolated at once: their temporaries (64 kB each) stay in the processor's cache, and below the
# size from which malloc maps fresh pages for every array.
POSITIONS_PER_CHUNK = 2**13


def pairs_within(points: NDArray, radius: float) -> NDArray[np.intp]:
    """Index pairs (P, 2), i < j in each, of the points (n, k) at most ``radius`` apart.

    The pairs of ``scipy.spatial.cKDTree(points).query_pairs(radius, output_type="ndarray")``, in another order.
    """
    p = _as_points(points)
    if p.shape[0] < 2 or not radius >= 0:
        return np.zeros((0, 2), dtype=np.intp)
    # A hair above the radius: points exactly one radius apart must not be two cells apart after rounding.
    grid = _CellGrid(p, radius * (1 + 1e-9))
    coordinates = [np.ascontiguousarray(p[grid.order, axis]) for axis in range(p.shape[1])]  # in the sorted order
    low, high = [np.zeros(0, dtype=np.intp)], [np.zeros(0, dtype=np.intp)]
    for first, second, counts in _later_neighbours(grid):
        squared = (np.repeat(coordinates[0][first], counts) - coordinates[0][second]) ** 2
        for axis in range(1, p.shape[1]):
            squared += (np.repeat(coordinates[axis][first], counts) - coordinates[axis][second]) ** 2
        near = np.flatnonzero(squared <= radius * radius)
        a, b = grid.order[np.repeat(first, counts)[near]], grid.order[second[near]]
        low.append(np.minimum(a, b))
        high.append(np.maximum(a, b))
    return np.stack([np.concatenate(low), np.concatenate(high)], axis=1)


class NearestPoints:
    """The nearest point of a fixed set (n, k) to given positions: ``scipy.spatial.cKDTree(points).query``.

    Among points equally near, the lowest index wins (cKDTree picks any of them). Small searches compare every
    position with every point; large ones descend a tree of cells (:class:`_CellTree`), built at the first of them.
    """

    def __init__(self, points: NDArray):
        self.points = _as_points(points)
        self._tree: _CellTree | None = None

    def nearest(self, positions: NDArray) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
        """Distance (m,) to the nearest point of the set and its index (m,), for positions (m, k); inf and n
        (the number of points) where the set is empty."""
        return self._search(_as_points(positions), None)

    def nearest_other(self) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
        """Distance (n,) from each point of the set to the nearest other one and that one's index (n,): the
        second neighbour of ``cKDTree(points).query(points, k=2)``; inf and n where the set has one point."""
        return self._search(self.points, np.arange(self.points.shape[0]))

    def _search(self, positions: NDArray, own: NDArray | None) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
        n, m = self.points.shape[0], positions.shape[0]
        if n == 0 or m == 0:
            return np.full(m, np.inf), np.full(m, n, dtype=np.intp)
        if n * m <= BRUTE_FORCE_PAIRS:
            return _nearest_by_comparison(self.points, positions, own)
        if self._tree is None:
            self._tree = _CellTree(self.points)
        return _distances(*self._tree.nearest(positions, own), n)


def bilinear(values: NDArray, rows: NDArray, columns: NDArray) -> NDArray[np.float64]:
    """A grid of values (H, W) interpolated bilinearly at fractional grid positions ``rows``, ``columns`` (any
    shape, the same for both); beyond the grid its edge values continue.

    ``scipy.ndimage.map_coordinates(values, (rows, columns), order=1, mode="nearest")`` to the last bit: the same
    weights (1 - f and 1 - (1 - f) for the fraction f of a position), each corner's value times its row weight
    and then its column weight, summed corner by corner in the same order.
    """
    grid = np.asarray(values, dtype=np.float64)
    y, x = np.broadcast_arrays(np.asarray(rows, dtype=np.float64), np.asarray(columns, dtype=np.float64))
    out = np.empty(y.shape)
    if out.size == 0:
        return out
    flat_out, flat_y, flat_x = out.reshape(-1), y.reshape(-1), x.reshape(-1)
    padded = _edge_padded(grid)
    for start in range(0, flat_y.size, POSITIONS_PER_CHUNK):
        chunk = slice(start, start + POSITIONS_PER_CHUNK)
        flat_out[chunk] = _bilinear_chunk(padded, flat_y[chunk], flat_x[chunk])
    return out


# --- grids of cells ----------------------------------------------------------------------------------------


class _CellGrid:
    """Points (n, k) sorted by the cubic cell of side ``side`` they lie in, counted from the points' lowest corner.

    ``order`` sorts the points by cell; ``point_cells`` (n, k) are the sorted points' cells; each occupied cell has
    its key (``cell_keys``, ascending) and the range of sorted points in it (``starts``, ``counts``).
    """

    def __init__(self, points: NDArray, side: float):
        self.origin = points.min(0)
        extent = float((points.max(0) - self.origin).max())
        # Cell keys of all axes together stay within int64, with a cell to spare on each side for the neighbours.
        cells_per_axis = 2 ** (62 // points.shape[1])
        self.side = max(side, extent / (cells_per_axis - 4), np.finfo(np.float64).tiny)
        self.shape = np.floor((points.max(0) - self.origin) / self.side).astype(np.int64) + 1
        cells = np.floor((points - self.origin) / self.side).astype(np.int64)
        keys = self.keys(cells)
        self.order = np.argsort(keys, kind="stable")
        self.point_cells = cells[self.order]
        self.cell_keys, self.starts, self.counts = np.unique(keys[self.order], return_index=True, return_counts=True)

    def keys(self, cells: NDArray) -> NDArray[np.int64]:
        """Keys (m,) of cells (m, k); -1 for a cell outside the grid."""
        inside = ((cells >= 0) & (cells < self.shape)).all(1)
        key = np.zeros(cells.shape[0], dtype=np.int64)
        for axis in range(cells.shape[1]):
            key = key * self.shape[axis] + cells[:, axis]
        return np.where(inside, key, -1)

    def ranges(self, cells: NDArray) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """First sorted point (m,) and number of points (m,) in each cell (m, k): 0 points in an empty one."""
        keys = self.keys(cells)
        at = np.minimum(np.searchsorted(self.cell_keys, keys), self.cell_keys.size - 1)
        occupied = (self.cell_keys[at] == keys) & (keys >= 0)
        return np.where(occupied, self.starts[at], 0), np.where(occupied, self.counts[at], 0)


def _offsets(dimensions: int, forward: bool = False) -> NDArray[np.int64]:
    """The cells around a cell and the cell itself, as offsets (3^k, k); ``forward``: only the cell itself and
    the half of the others that come after it, so that each pair of neighbouring cells is visited once."""
    steps = list(itertools.product((-1, 0, 1), repeat=dimensions))
    if forward:
        steps = [step for step in steps if step >= (0,) * dimensions]
    return np.array(steps, dtype=np.int64).reshape(len(steps), dimensions)


def _later_neighbours(grid: _CellGrid) -> Iterator[tuple[NDArray, NDArray, NDArray]]:
    """Every pair of sorted points in the same or neighbouring cells once, the later point second, in chunks of
    about :data:`CANDIDATES_PER_CHUNK` pairs. A chunk is r ranges of second points: each range's first point (r,),
    the second points of all ranges one after the other, and each range's length (r,)."""
    n = grid.order.size
    offsets = _offsets(grid.point_cells.shape[1], forward=True)  # the cell itself first
    starts, counts = grid.ranges((grid.point_cells[:, None, :] + offsets[None]).reshape(n * offsets.shape[0], -1))
    starts, counts = starts.reshape(n, -1), counts.reshape(n, -1)
    # Within its own cell a point pairs with the points after it.
    position = np.arange(n)
    counts[:, 0] = starts[:, 0] + counts[:, 0] - position - 1
    starts[:, 0] = position + 1
    for rows in _chunks(counts.sum(1), CANDIDATES_PER_CHUNK):
        first = np.repeat(position[rows], offsets.shape[0])
        yield first, _positions(starts[rows].ravel(), counts[rows].ravel()), counts[rows].ravel()


def _chunks(counts: NDArray, limit: int) -> list[slice]:
    """Consecutive ranges of rows whose ``counts`` add up to about ``limit`` (a row above it alone)."""
    if counts.size == 0:
        return []
    total = np.cumsum(counts)
    cuts = np.searchsorted(total, np.arange(limit, total[-1], limit), side="right")
    edges = np.unique(np.concatenate([[0], cuts, [counts.size]]))
    return [slice(int(start), int(stop)) for start, stop in itertools.pairwise(edges)]


def _expand(rows: NDArray, starts: NDArray, counts: NDArray) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """(row, position) for every position of each row's range [start, start + count)."""
    return np.repeat(rows, counts), _positions(starts, counts)


def _positions(starts: NDArray, counts: NDArray) -> NDArray[np.intp]:
    """The positions of the ranges [start, start + count), one range after the other."""
    first_of_range = np.cumsum(counts) - counts
    return np.arange(int(counts.sum())) + np.repeat(starts - first_of_range, counts)


# --- nearest points ----------------------------------------------------------------------------------------


def _nearest_by_comparison(points: NDArray, positions: NDArray, own: NDArray | None
                           ) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """:meth:`NearestPoints._search` by the distances of every position to every point, rows at a time."""
    n, m = points.shape[0], positions.shape[0]
    distance2 = np.empty(m)
    index = np.empty(m, dtype=np.intp)
    step = max(1, CANDIDATES_PER_CHUNK // n)
    for start in range(0, m, step):
        rows = np.arange(start, min(start + step, m))
        squared = _squared_distance_table(positions[rows], points)
        if own is not None:
            squared[np.arange(rows.size), own[rows]] = np.inf
        index[rows] = squared.argmin(1)  # the first of equal minima: the lowest index
        distance2[rows] = squared[np.arange(rows.size), index[rows]]
    return _distances(distance2, index, n)


class _CellTree:
    """Points (n, k) in cells halved level by level: an octree in arrays (a quadtree in two dimensions).

    The top level is one cell holding every point; each level below halves the cells' side, down to the level
    where every cell is a leaf: at most :data:`LEAF_POINTS` points, or points that no halving separates. The
    points are sorted along the Z-order curve of the finest cells, so every cell of every level holds a
    contiguous range of them. Per level, from the top: each cell's first point (``starts``), number of points,
    integer coordinates, whether it is a leaf, and its first child and number of children on the level below.
    """

    def __init__(self, points: NDArray):
        k = points.shape[1]
        bits = 62 // k  # the Z-order codes of all axes stay within int64
        self.origin = points.min(0)
        extent = float((points.max(0) - self.origin).max())
        self.finest_side = max(extent / (2**bits - 1), np.finfo(np.float64).tiny)
        cells = np.floor((points - self.origin) / self.finest_side).astype(np.int64)
        codes = _z_order(cells, bits)
        self.order = np.argsort(codes, kind="stable")
        self.points, self.codes = points[self.order], codes[self.order]
        self.shifts, self.starts, self.counts, self.cells, self.leaf = _tree_levels(self.codes, cells[self.order], k)
        self.first_child, self.children = _tree_children(self.codes, self.starts, self.shifts, k)

    def nearest(self, positions: NDArray, own: NDArray | None) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
        """Squared distance (m,) to the nearest point and its index (m,) (sorted order undone), for positions (m, k)
        and, where given, the index of each position's own point (m,) that does not count; inf and n where none.

        From the top level down, each position keeps the cells no farther from it than the nearest point seen so
        far (points near it along the Z-order curve to begin with, then those of the leaves it compared), compares
        the points of its leaves and goes on into the children of its other cells.
        """
        n = self.points.shape[0]
        distance2, index = np.full(positions.shape[0], np.inf), np.full(positions.shape[0], n, dtype=np.intp)
        step = max(1, CANDIDATES_PER_CHUNK // 64)  # a position keeps some tens of cells and candidates per level
        own_sorted = None if own is None else np.argsort(self.order)[own]  # own points in the sorted order
        for start in range(0, positions.shape[0], step):
            rows = slice(start, start + step)
            distance2[rows], index[rows] = self._nearest_of(positions[rows],
                                                            None if own_sorted is None else own_sorted[rows])
        return distance2, index

    def _nearest_of(self, positions: NDArray, own_sorted: NDArray | None
                    ) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
        """:meth:`nearest` of a chunk of positions, their own points given in the sorted order."""
        m, n = positions.shape[0], self.points.shape[0]
        best2, best = np.full(m, np.inf), np.full(m, n, dtype=np.intp)
        bound2 = self._curve_neighbours2(positions, own_sorted)  # the least squared distance seen
        rows, cell = np.arange(m), np.zeros(m, dtype=np.intp)
        for level in range(len(self.shifts)):
            at = positions[rows]
            self._lower_by_first_points(at, own_sorted, rows, self.starts[level][cell], bound2)
            np.minimum(bound2, best2, out=bound2)
            keep = self._box_distance2(at, level, cell) <= bound2[rows]
            rows, cell = rows[keep], cell[keep]
            leaf = self.leaf[level][cell]
            self._compare_leaves(positions, own_sorted, rows[leaf], cell[leaf], level, best2, best)
            if level + 1 < len(self.shifts):
                rows, cell = _expand(rows[~leaf], self.first_child[level][cell[~leaf]],
                                     self.children[level][cell[~leaf]])
        return best2, best

    def _curve_neighbours2(self, positions: NDArray, own_sorted: NDArray | None) -> NDArray[np.float64]:
        """Squared distance (m,) from each position to the nearest of the two points on either side of it along
        the Z-order curve (not its own point): points near on the curve mostly lie near in space, so this bounds
        the search from the start."""
        k, n = positions.shape[1], self.points.shape[0]
        with np.errstate(over="ignore"):  # the finest side of a set of equal points is the tiniest float
            cells = np.floor((positions - self.origin) / self.finest_side)
        codes = _z_order(np.clip(np.nan_to_num(cells), 0, 2 ** (62 // k) - 1).astype(np.int64), 62 // k)
        after = np.searchsorted(self.codes, codes)
        nearest2 = np.full(positions.shape[0], np.inf)
        for step in (-2, -1, 0, 1):  # a position's own point sits before or after it: two each side
            neighbour = np.clip(after + step, 0, n - 1)
            squared = _squared_distances(positions, self.points[neighbour])
            if own_sorted is not None:
                squared[neighbour == own_sorted] = np.inf
            np.minimum(nearest2, squared, out=nearest2)
        return nearest2

    def _lower_by_first_points(self, at: NDArray, own_sorted: NDArray | None, rows: NDArray, first: NDArray,
                               bound2: NDArray) -> None:
        """Lower the bounds ``bound2`` of positions ``at`` (rows ``rows``, grouped) to the squared distances of
        their cells' first points ``first``: far from every point, a position's neighbours along the curve may
        lie far from its nearest point."""
        if rows.size == 0:
            return
        squared = _squared_distances(at, self.points[first])
        if own_sorted is not None:
            squared[first == own_sorted[rows]] = np.inf
        groups = _group_starts(rows)
        bound2[rows[groups]] = np.minimum(bound2[rows[groups]], np.minimum.reduceat(squared, groups))

    def _compare_leaves(self, positions: NDArray, own_sorted: NDArray | None, rows: NDArray, cell: NDArray,
                        level: int, best2: NDArray, best: NDArray) -> None:
        """Update the least squared distances ``best2`` and their points ``best`` (lowest index among equals) of
        positions with the points of their leaves ``cell`` on ``level``."""
        rows, candidate = _expand(rows, self.starts[level][cell], self.counts[level][cell])
        squared = _squared_distances(positions[rows], self.points[candidate])
        if own_sorted is not None:
            squared[candidate == own_sorted[rows]] = np.inf
        found2, found = _lowest_per_row(rows, squared, self.order[candidate], best2.size, self.points.shape[0])
        better = (found2 < best2) | ((found2 == best2) & (found < best))
        best2[better], best[better] = found2[better], found[better]

    def _box_distance2(self, positions: NDArray, level: int, cell: NDArray) -> NDArray[np.float64]:
        """Squared distance (m,) from positions (m, k) to the boxes of cells of ``level``, each a hair larger
        than its side so that rounding never puts a point outside its cell's box."""
        side = self.finest_side * 2.0 ** self.shifts[level]
        low = self.origin + self.cells[level][cell] * side - 1e-9 * side
        gap = np.maximum(np.maximum(low - positions, positions - (low + side * (1 + 2e-9))), 0.0)
        return _squared_distances(gap, np.zeros_like(gap))


def _tree_levels(codes: NDArray, cells: NDArray, k: int
                 ) -> tuple[list[int], list[NDArray], list[NDArray], list[NDArray], list[NDArray]]:
    """The levels of a :class:`_CellTree` from the top, for its sorted Z-order codes (n,) and finest cells (n, k):
    per level the shift of its codes in bits per axis, and per cell its first point, its number of points, its
    integer coordinates and whether it is a leaf."""
    shifts: list[int] = []
    starts, counts, level_cells, leaf = [], [], [], []
    for shift in range(62 // k, -1, -1):
        start = _group_starts(codes >> (k * shift))
        count = np.diff(np.append(start, codes.size))
        shifts.append(shift)
        starts.append(start)
        counts.append(count)
        level_cells.append(cells[start] >> shift)
        leaf.append((count <= LEAF_POINTS) | (codes[start] == codes[start + count - 1]) | (shift == 0))
        if leaf[-1].all():
            break
    return shifts, starts, counts, level_cells, leaf


def _tree_children(codes: NDArray, starts: list[NDArray], shifts: list[int], k: int
                   ) -> tuple[list[NDArray], list[NDArray]]:
    """Per level of a :class:`_CellTree` but the last, each cell's first child on the level below and its number
    of children."""
    first_child, children = [], []
    for level in range(len(shifts) - 1):
        parents = codes[starts[level + 1]] >> (k * shifts[level])  # of the cells one level down
        first = _group_starts(parents)
        first_child.append(first)
        children.append(np.diff(np.append(first, parents.size)))
    return first_child, children


def _z_order(cells: NDArray, bits: int) -> NDArray[np.int64]:
    """Z-order codes (n,) of integer cells (n, k) below 2^bits: their coordinates' bits interleaved."""
    k = cells.shape[1]
    codes = np.zeros(cells.shape[0], dtype=np.int64)
    for bit in range(bits):
        for axis in range(k):
            codes |= ((cells[:, axis] >> bit) & 1) << (bit * k + axis)
    return codes


def _lowest_per_row(rows: NDArray, squared: NDArray, candidate: NDArray, m: int, n: int
                    ) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Per row of m: the least squared distance of its candidates (grouped by ascending row) and the lowest
    candidate index among those that reach it; inf and n for rows without candidates."""
    distance2, index = np.full(m, np.inf), np.full(m, n, dtype=np.intp)
    if rows.size == 0:
        return distance2, index
    first = _group_starts(rows)
    best = np.minimum.reduceat(squared, first)
    tied = squared == np.repeat(best, np.diff(np.append(first, rows.size)))
    distance2[rows[first]] = best
    index[rows[first]] = np.minimum.reduceat(np.where(tied, candidate, n), first)
    return distance2, index


def _group_starts(rows: NDArray) -> NDArray[np.intp]:
    """Where each run of equal values in ``rows`` (non-empty) begins."""
    return np.flatnonzero(np.concatenate([[True], rows[1:] != rows[:-1]]))


def _distances(distance2: NDArray, index: NDArray, n: int) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Distances from squared ones, and the index n (no point) where none was found."""
    return np.sqrt(distance2), np.where(np.isfinite(distance2), index, n)


# --- arithmetic --------------------------------------------------------------------------------------------


def _as_points(points: NDArray) -> NDArray[np.float64]:
    """Points as a float64 array (n, k); a flat array holds points of one coordinate."""
    p = np.asarray(points, dtype=np.float64)
    return p.reshape(-1, 1) if p.ndim == 1 else p


def _squared_distances(a: NDArray, b: NDArray) -> NDArray[np.float64]:
    """Squared distances (n,) between rows of a (n, k) and b (n, k), summed axis by axis as cKDTree sums them."""
    total = (a[:, 0] - b[:, 0]) ** 2
    for axis in range(1, a.shape[1]):
        total += (a[:, axis] - b[:, axis]) ** 2
    return total


def _squared_distance_table(a: NDArray, b: NDArray) -> NDArray[np.float64]:
    """Squared distances (n, m) of every row of a (n, k) to every row of b (m, k), summed axis by axis."""
    total = (a[:, 0, None] - b[None, :, 0]) ** 2
    for axis in range(1, a.shape[1]):
        total += (a[:, axis, None] - b[None, :, axis]) ** 2
    return total


def _edge_padded(grid: NDArray) -> NDArray[np.float64]:
    """The grid (H, W) with a border of its edge values: the corners of positions up to one cell beyond the grid
    need no clipping. np.pad does the same at three times the cost, which counts for the many small grids."""
    h, w = grid.shape
    padded = np.empty((h + 2, w + 2))
    padded[1:-1, 1:-1] = grid
    padded[0, 1:-1], padded[-1, 1:-1] = grid[0], grid[-1]
    padded[:, 0], padded[:, -1] = padded[:, 1], padded[:, -2]
    return padded


def _bilinear_chunk(padded: NDArray, rows: NDArray, columns: NDArray) -> NDArray[np.float64]:
    """:func:`bilinear` of positions (n,) on a grid padded with one cell of its edge values on each side."""
    height, width = padded.shape[0] - 2, padded.shape[1] - 2
    top, left = np.floor(rows), np.floor(columns)
    upper = 1.0 - (rows - top)  # the row weight of the upper corners, scipy's 1 - f
    lower = 1.0 - upper
    before = 1.0 - (columns - left)
    after = 1.0 - before
    top += 1  # rows and columns of the padded grid
    left += 1
    if top.size and (top.min() < 0 or top.max() > height or left.min() < 0 or left.max() > width):
        # Beyond one cell outside the grid both corners of an axis are its edge value.
        np.clip(top, 0, height, out=top)
        np.clip(left, 0, width, out=left)
    corner = top.astype(np.intp) * padded.shape[1] + left.astype(np.intp)
    flat = padded.reshape(-1)
    stride = padded.shape[1]
    out = flat.take(corner) * upper
    out *= before
    for start, row_weight, column_weight in ((1, upper, after), (stride, lower, before), (stride + 1, lower, after)):
        term = flat[start:].take(corner) * row_weight
        term *= column_weight
        out += term
    return out
