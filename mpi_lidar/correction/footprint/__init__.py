"""Self-calibration of the receiver footprint: a scan measures its own multipath strength.

How much light a facing surface sends back scales with one sensor constant, the effective receiver footprint
A_fp (:mod:`mpi_lidar.physics.coupling`). A scan holds the evidence for it: on two surfaces that face each other
the raw depth drifts away from the surfaces' planes towards their shared edge, in proportion to A_fp and with the
shape the geometry predicts, and multipath adds light as well as range. :func:`estimate_footprint` fits A_fp to
both; :class:`PlaneModelInputs` gives a geometric correction model its per-pixel inputs at a footprint.
docs/explanation/footprint.md carries the equations (F1)-(F15) the modules cite; (F16), the two bounces, is in
``_two_bounce``.

The parts, each private: ``_surfaces`` (the scan's flat surfaces), ``_albedo`` (albedo from amplitude),
``_partners`` (flat surfaces as planes continued beyond the view), ``_facing_pairs`` (which surfaces meet and
face, and the block pairs no plane describes), ``_two_bounce`` (light from one partner plane to
another and back, A -> B -> C -> A), ``_coupling`` (the multipath model's phasors),
``_problem`` (the fit's rows, bias model and planes), ``_fit`` (the weighted fit of the footprint), ``_result``
(:class:`FootprintEstimate`), ``_estimate`` (the rounds of the fit), ``_inputs`` (the model's inputs).
"""

from __future__ import annotations

from mpi_lidar.correction.footprint._albedo import block_albedo, white_albedo
from mpi_lidar.correction.footprint._estimate import estimate_footprint, unbent_planes
from mpi_lidar.correction.footprint._inputs import PlaneModelInputs, plane_model_inputs
from mpi_lidar.correction.footprint._result import (
    MIN_INFORMATIVE_PIXELS,
    MIN_SIGNIFICANCE,
    NOTHING_MEASURED,
    EstimateMethod,
    FootprintEstimate,
    pool_estimates,
)
from mpi_lidar.correction.footprint._surfaces import SurfaceLabels, surface_labels

__all__ = [
    "MIN_INFORMATIVE_PIXELS", "MIN_SIGNIFICANCE", "NOTHING_MEASURED", "EstimateMethod", "FootprintEstimate",
    "PlaneModelInputs", "SurfaceLabels", "block_albedo", "estimate_footprint", "plane_model_inputs",
    "pool_estimates", "surface_labels", "unbent_planes", "white_albedo",
]
