"""The single-bounce coupling of points on one plane with the patches of another: kappa (F4) and its phasor at
each frequency, summed over the patches in chunks (docs/explanation/footprint.md)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.scans.geometry import DEFAULT_MIN_COS

if TYPE_CHECKING:
    pass

# Above this many pixel-patch pairs the coupling is summed in chunks (memory stays near 100 MB).
PAIRS_PER_CHUNK = 2_000_000


def coupling_at(points: NDArray, normal_a: NDArray, centres_b: NDArray, area_b: NDArray, normal_b: NDArray,
                 frequencies_hz: tuple[float, ...], speed_of_light_m_per_s: float) -> NDArray[np.complex128]:
    """Per receiving point (n,) on one plane (normal ``normal_a``): [kappa, phasor at each frequency]
    (n, 1 + F) summed over the patches of another plane (normal ``normal_b``).

    kappa (F4) = (cos_A cos_B)^2 dA_B / (pi^2 max(r, sqrt(dA_B))^4 cos_i) at A_fp = 1 m^2, the renderer's
    :func:`mpi_lidar.physics.coupling.footprint_coupling`, with r cos_A and r cos_B from the offsets along the
    two normals (each side lies on one plane, so they split into a point's and a patch's part).
    """
    rays = points / np.maximum(np.linalg.norm(points, axis=1, keepdims=True), 1e-12)
    cos_i = np.maximum(-dot3(rays, normal_a), 1e-3).astype(np.float32)
    # Single precision about the patches' mean: offsets of centimetres to metres (the phases and sums are
    # accumulated in double precision).
    origin = centres_b.mean(0)
    a, b = (points - origin).astype(np.float32), (centres_b - origin).astype(np.float32)
    normal_a, normal_b = np.asarray(normal_a, dtype=np.float32), np.asarray(normal_b, dtype=np.float32)
    area_b = area_b.astype(np.float32)
    wavenumbers = 4 * np.pi * np.asarray(frequencies_hz, dtype=np.float64) / speed_of_light_m_per_s
    out = np.zeros((points.shape[0], 1 + wavenumbers.size), dtype=np.complex128)
    chunks = max(1, points.shape[0] * b.shape[0] // PAIRS_PER_CHUNK)
    for rows in np.array_split(np.arange(points.shape[0]), chunks):
        offset = b[None] - a[rows, None]
        r2 = np.maximum(np.einsum("nmk,nmk->nm", offset, offset), np.float32(1e-12))
        along_a = dot3(b, normal_a)[None] - dot3(a[rows], normal_a)[:, None]  # r cos_A
        along_b = dot3(a[rows], normal_b)[:, None] - dot3(b, normal_b)[None]  # r cos_B
        r = np.sqrt(r2)
        facing = (along_a > DEFAULT_MIN_COS * r) & (along_b > DEFAULT_MIN_COS * r)
        r_eff2 = np.maximum(r2, area_b[None])
        kappa = np.where(facing, (along_a * along_b / r2) ** 2 * area_b[None] / (np.float32(np.pi**2) * r_eff2**2),
                         np.float32(0.0)) / cos_i[rows, None]
        out[rows, 0] = kappa.sum(1)
        out[rows, 1:] = phasor_sums(kappa, r, wavenumbers)
    return out


def dot3(vectors: NDArray, normal: NDArray) -> NDArray:
    """Each vector (..., 3) dotted with one (3,), element by element: BLAS's matrix-vector product rounds a row
    differently with the number of rows it comes with (on some CPUs), and a pixel's value must not depend on the
    tile or chunk it was worked out in."""
    return vectors[..., 0] * normal[0] + vectors[..., 1] * normal[1] + vectors[..., 2] * normal[2]


def phasor_sums(kappa: NDArray, r: NDArray, wavenumbers: NDArray) -> NDArray[np.complex128]:
    """sum_m kappa e^{j k r} over the last axis, per wavenumber k (n, K).

    Where the wavenumbers are small multiples of a common one (the sensor's frequencies are: 2, 3, 4 and 5
    times 6.25 MHz) one complex exponential and its powers replace a cosine and a sine per frequency.
    """
    if wavenumbers.size == 1:
        # One frequency (a correction model's inputs): its cosine and sine in single precision, as r is, and
        # summed in double; a complex exponential costs several times more.
        phase = np.float32(wavenumbers[0]) * r
        return ((kappa * np.cos(phase)).sum(1, dtype=np.float64)
                + 1j * (kappa * np.sin(phase)).sum(1, dtype=np.float64))[:, None]
    multiples = _common_multiples(wavenumbers)
    if multiples is None:
        return np.stack([(kappa * np.cos(k * r)).sum(1) + 1j * (kappa * np.sin(k * r)).sum(1) for k in wavenumbers],
                        axis=1)
    base = np.exp(1j * (wavenumbers[0] / multiples[0]) * r.astype(np.float64))
    power, sums, current = kappa * base ** multiples[0], [], multiples[0]
    for multiple in multiples:
        while current < multiple:
            power *= base
            current += 1
        sums.append(power.sum(1))
    return np.stack(sums, axis=1)


def _common_multiples(wavenumbers: NDArray, largest: int = 8) -> NDArray[np.intp] | None:
    """Integers n (ascending, each at most ``largest``) with wavenumbers = n k0, or None."""
    for lowest in range(1, largest + 1):
        multiples = wavenumbers / wavenumbers[0] * lowest
        rounded = np.rint(multiples)
        if np.allclose(multiples, rounded, rtol=0, atol=1e-9) and rounded.max() <= largest \
                and np.all(np.diff(rounded) > 0):
            return rounded.astype(np.intp)
    return None
