"""Gates: which valid pixels need correction, so that correction does no harm where a scene has no multipath.

A gate is a policy, not a computation: it decides from what the scene-geometry stage found
(:class:`mpi_lidar.correction.scene.SceneGeometry`) and, pixel by pixel, from the raw measurements. It holds no
state, so one gate may decide any number of scans. :class:`mpi_lidar.correction.options.GateName` names them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.options import CorrectionOptions, GateName
from mpi_lidar.physics.noise import NoiseModel

if TYPE_CHECKING:
    from mpi_lidar.correction.scene import SceneGeometry


@dataclass(frozen=True)
class Gate:
    """Decides which valid pixels need correction.

    Contract: :meth:`candidates` takes the scan's :class:`SceneGeometry` (None where the scan's geometry was not
    analysed) and returns a bool (H*W,) of the pixels that may need correction (the others get NO_MULTIPATH),
    or None where every pixel may. :meth:`needs_correction` takes the raw measurements (n, 2F) of valid pixels
    [m, V^2] and the scan's noise model and returns a bool (n,): True where the model should correct; it must be
    much cheaper than inference, since its purpose is to skip work. Both are pure functions of their arguments.
    ``uses_geometry`` says whether the gate needs the scene's geometry analysed, ``pixel_wise`` whether
    :meth:`needs_correction` decides anything (the validity pass then asks it for every valid pixel).
    """

    name: ClassVar[GateName]
    uses_geometry: ClassVar[bool] = False
    pixel_wise: ClassVar[bool] = False

    def candidates(self, scene: SceneGeometry | None) -> NDArray[np.bool_] | None:
        """Bool (H*W,) of pixels that may need correction, from the whole scan; None: every pixel may."""
        return None

    def needs_correction(self, raw: NDArray, noise: NoiseModel) -> NDArray[np.bool_]:
        """Bool (n,) of the valid pixels (raw rows (n, 2F)) the model should correct: here every one."""
        return np.ones(raw.shape[0], dtype=bool)


@dataclass(frozen=True)
class CorrectAll(Gate):
    """Every valid pixel is corrected (the paper's pixel-wise correction)."""

    name: ClassVar[GateName] = GateName.ALL


@dataclass(frozen=True)
class ConsistencyGate(Gate):
    """Corrects pixels whose per-frequency depths disagree by more than their predicted noise allows.

    A pixel with no multipath has the same depth at every frequency up to noise; chi^2 of the depths around
    their inverse-variance mean, with each depth's noise predicted by the moment model at the measured
    amplitude (:meth:`mpi_lidar.physics.noise.NoiseModel.disagree`), follows chi^2(F-1) (a degree fewer per
    frequency without light).
    Pixels below the (1 - p) quantile are skipped. At Table I noise and d_AB <= 15 cm the multipath offset
    is almost the same at every frequency, so this test misses most multipath: it is cheap, not sufficient.
    """

    name: ClassVar[GateName] = GateName.CONSISTENCY
    pixel_wise: ClassVar[bool] = True
    p_value: float = 0.01

    def needs_correction(self, raw: NDArray, noise: NoiseModel) -> NDArray[np.bool_]:
        return noise.disagree(raw, self.p_value)


@dataclass(frozen=True)
class GeometryGate(Gate):
    """Corrects only pixels where the scan's geometry allows multipath.

    A pixel is a candidate where the expected multipath bias of its facing surfaces
    (:attr:`SceneGeometry.reaches_min_bias`) reaches ``CorrectionOptions.min_multipath_bias_m``; flat walls,
    convex objects and open sky have none. Scans without geometry (no rays or scan grid) get None: every valid
    pixel is corrected, pixel-wise.
    """

    name: ClassVar[GateName] = GateName.GEOMETRY
    uses_geometry: ClassVar[bool] = True

    def candidates(self, scene: SceneGeometry | None) -> NDArray[np.bool_] | None:
        return None if scene is None else scene.reaches_min_bias


def make_gate(options: CorrectionOptions) -> Gate:
    """The gate ``options.gate`` names."""
    gates = {GateName.ALL: CorrectAll, GateName.CONSISTENCY: lambda: ConsistencyGate(options.consistency_p_value),
             GateName.GEOMETRY: GeometryGate}
    return gates[GateName(options.gate)]()
