"""The A -> B -> A coupling kernel: how much light a patch of surface B sends back to the pixel at A.

The beam lights point A, seen at incidence cos_i. A Lambertian A (albedo a) scatters a fraction
a cos_A cos_B dA_B / (pi r^2) of its light onto a patch B of area dA_B at distance r (cos_A, cos_B: the
cosines between the line A-B and the two surface normals); the patch (albedo b) returns
b cos_B cos_A A_fp / (pi r^2) of that onto the receiver footprint A_fp around A; and A scatters it to the
sensor like the direct light, which itself carried a cos_i. Relative to the direct path the patch adds

    Gamma_M,B / Gamma_D = a b kappa_B,    kappa_B = (cos_A cos_B)^2 dA_B A_fp / (pi^2 r^4 cos_i),

with the phase of the longer path, 4 pi f (d_AS + r) / c (eq 13, 15). Summed over the patches, kappa is
the coupling of the paper's reciprocal prior (ratio Gamma_M / Gamma_D = a kappa b). Both the scene
renderer (:func:`mpi_lidar.simulation.scenes.light_transport`, with the true surfaces and their
tessellation) and the geometry gate (:func:`mpi_lidar.scans.geometry.multipath_potential`, with planes
fitted to a scan's blocks) evaluate this one kernel; each decides for itself which pairs face each other,
how far r is clamped below (the finite beam smooths the 1/r^4 singularity at a corner line) and caps the
sum at kappa = 1 (A cannot get back more than all its light through B).

Calibration of the footprint. With Lambertian boards and a footprint of radius 12 mm the integral gives a
90-degree corner a ratio Gamma_M / Gamma_D of about 3.8e-6 m^2 / a^2 at a distance a from the edge
(closed form: a b A_fp 0.1309 / (pi^2 a^2 cos_i)), some 50 times less multipath than the paper measured
on its cornered board (Fig. 7: 5.0 mm raw MAE, 2.4 cm at most). Real boards are not Lambertian and the
receiver's field of view is not given, so the footprint is scaled by a gain, :data:`DEFAULT_COUPLING_GAIN`,
calibrated to Fig. 7: at 90 the cornered board shows a raw 31.25 MHz MAE near 5 mm on its reference mask
and about 2.4 cm at the corner. The effective footprint is therefore A_fp = gain * pi r_fp^2
(:data:`DEFAULT_FOOTPRINT_AREA_M2` = 90 pi (12 mm)^2).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

DEFAULT_FOOTPRINT_RADIUS_M = 0.012
DEFAULT_COUPLING_GAIN = 90.0


def footprint_area(radius_m: float, gain: float = DEFAULT_COUPLING_GAIN) -> float:
    """Effective receiver footprint A_fp = gain * pi * radius^2 of the coupling. [m^2]

    Parameters
    ----------
    radius_m : Radius of the receiver footprint around A. [m]
    gain : Calibration gain of the footprint (see the module docstring). [1]
    """
    return gain * np.pi * radius_m**2


DEFAULT_FOOTPRINT_AREA_M2 = footprint_area(DEFAULT_FOOTPRINT_RADIUS_M, DEFAULT_COUPLING_GAIN)


def vector_length(vectors: NDArray) -> NDArray[np.float64]:
    """Euclidean length over the last axis (3): np.linalg.norm(vectors, axis=-1), the same numbers, at a
    quarter of the cost (NumPy's reduction over a short last axis is slow)."""
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    return np.sqrt(x * x + y * y + z * z)


def pair_geometry(points_a: ArrayLike, normals_a: ArrayLike, points_b: ArrayLike, normals_b: ArrayLike
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Distance and facing cosines of point pairs A, B (arrays broadcast against each other).

    Parameters
    ----------
    points_a : Points A, shape (..., 3). [m]
    normals_a : Unit normals at A, shape (..., 3). [1]
    points_b : Points B (patch centres), shape (..., 3). [m]
    normals_b : Unit normals at B, shape (..., 3). [1]

    Returns
    -------
    r : Distance |B - A|, shape (...). [m]
    cos_a : Cosine between the direction A -> B and A's normal; > 0 where B lies in front of A. [1]
    cos_b : Cosine between the direction B -> A and B's normal; > 0 where A lies in front of B. [1]
    """
    offset = np.asarray(points_b, dtype=np.float64) - np.asarray(points_a, dtype=np.float64)
    r = vector_length(offset)
    direction = offset / np.maximum(r, 1e-12)[..., None]
    cos_a = np.einsum("...k,...k->...", direction, np.asarray(normals_a, dtype=np.float64))
    cos_b = -np.einsum("...k,...k->...", direction, np.asarray(normals_b, dtype=np.float64))
    return r, cos_a, cos_b


def footprint_coupling(cos_a: ArrayLike, cos_b: ArrayLike, area_b_m2: ArrayLike, r_m: ArrayLike, cos_i: ArrayLike,
                       footprint_area_m2: float, reflectance: ArrayLike = 1.0) -> NDArray[np.float64]:
    """Coupling of a patch B back to A: reflectance (cos_A cos_B)^2 dA_B A_fp / (pi^2 r^4 cos_i).

    With ``reflectance`` = 1 this is kappa_B (white surfaces); with the product a b of the two albedos it is
    the patch's ratio Gamma_M,B / Gamma_D. The caller masks out pairs that do not face each other (the
    formula assumes cos_A, cos_B > 0) and clamps r and cos_i away from 0. All arguments broadcast.

    Parameters
    ----------
    cos_a : Cosine at A between its normal and the direction to B. [1]
    cos_b : Cosine at B between its normal and the direction to A. [1]
    area_b_m2 : Area of the patch B. [m^2]
    r_m : Distance from A to B (clamped below by the caller). [m]
    cos_i : Incidence cosine of the beam at A (clamped below by the caller). [1]
    footprint_area_m2 : Effective receiver footprint A_fp around A, see :func:`footprint_area`. [m^2]
    reflectance : Albedo product a b of A and B, or 1 for kappa_B. [1]

    Returns
    -------
    kappa_B times the reflectance, shape of the broadcast arguments. [1]
    """
    def real(values: ArrayLike) -> NDArray[np.float64]:
        return np.asarray(values, dtype=np.float64)  # no copy for float64 input; the same values for any other

    weight = real(reflectance) * (real(cos_a) * real(cos_b)) ** 2 * real(area_b_m2) * footprint_area_m2
    return weight / (np.pi**2 * real(r_m) ** 4 * real(cos_i))
