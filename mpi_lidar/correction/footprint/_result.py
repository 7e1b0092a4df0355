"""What a footprint measurement found: :class:`FootprintEstimate`, and several scans' estimates pooled."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

# The estimate is used only when it is this many standard deviations above zero ...
MIN_SIGNIFICANCE = 3.0
# ... and rests on at least this many pixels with a facing partner.
MIN_INFORMATIVE_PIXELS = 200


class EstimateMethod(StrEnum):
    """What the raw depth is measured against: the scan's own surface planes, or a reference depth."""

    PLANES = "planes"
    REFERENCE = "reference"


@dataclass(frozen=True)
class FootprintEstimate:
    """The receiver footprint a scan (or several) measured, and how sure it is.

    Attributes
    ----------
    area_m2 : float
        The estimate of A_fp, NaN where nothing could be measured. [m^2]
    sigma_m2 : float
        Its standard deviation, inf where nothing was measured. [m^2]
    pixels : int
        The pixels with a facing partner the fit rests on.
    surfaces : int
        The flat surfaces fitted.
    methods : tuple[EstimateMethod, ...]
        How the scans measured it (sorted, each once): against their planes or a reference depth.
    scans : int
        How many scans were pooled.
    white_surfaces : bool
        Whether it was measured with every surface taken as white (a scan whose amplitude unit is not known):
        then it is the footprint times the albedos the light returns from, not the receiver's own.
    systematic_share : float
        A relative uncertainty beyond ``sigma_m2`` that the blocks it was measured on leave (a coarse scan's
        finer blocks), which a corrected depth's uncertainty carries. The significance is judged without it:
        it scales with the estimate, so no estimate would pass 1 / share sigmas. [1]
    depth_m2, amplitude_m2 : float
        The depth's and the amplitude's own estimates before they were joined ((F13) of
        docs/explanation/footprint.md), NaN where the amplitude was not fitted (against a reference depth, several
        scans pooled). [m^2]
    """

    area_m2: float
    sigma_m2: float
    pixels: int
    surfaces: int
    methods: tuple[EstimateMethod, ...] = (EstimateMethod.PLANES,)
    scans: int = 1
    white_surfaces: bool = False
    systematic_share: float = 0.0
    depth_m2: float = float("nan")
    amplitude_m2: float = float("nan")

    @property
    def disagreement(self) -> float:
        """How far apart the depth's and the amplitude's estimates are, the larger over the smaller [1] (NaN where
        one of them is missing or not above zero)."""
        pair = (self.depth_m2, self.amplitude_m2)
        if not all(np.isfinite(pair)) or min(pair) <= 0:
            return float("nan")
        return float(max(pair) / min(pair))

    @property
    def relative_sigma(self) -> float:
        """The estimate's whole relative uncertainty [1] (inf where nothing was measured): in quadrature, its sd
        over it, the systematic share, and half the log distance between its depth's and its amplitude's
        measurements (the truth may lie nearer either; the significance is judged without the last two)."""
        if not np.isfinite(self.area_m2) or self.area_m2 <= 0 or not np.isfinite(self.sigma_m2):
            return float("inf")
        apart = self.disagreement
        measurements = 0.5 * float(np.log(apart)) if np.isfinite(apart) else 0.0
        return float(np.hypot(np.hypot(self.sigma_m2 / self.area_m2, self.systematic_share), measurements))

    @property
    def method(self) -> str:
        """The methods joined by "+" (e.g. "planes", "planes+reference"), as profiles and reports write them."""
        return "+".join(self.methods)

    @property
    def significance(self) -> float:
        """Estimate over its standard deviation (0 where nothing was measured)."""
        if not np.isfinite(self.area_m2) or not np.isfinite(self.sigma_m2) or self.sigma_m2 <= 0:
            return 0.0
        return self.area_m2 / self.sigma_m2

    @property
    def significant(self) -> bool:
        """Whether the estimate may decide pixels: ``MIN_SIGNIFICANCE`` sigmas above zero, on at least
        ``MIN_INFORMATIVE_PIXELS`` pixels."""
        return self.significance >= MIN_SIGNIFICANCE and self.pixels >= MIN_INFORMATIVE_PIXELS

    def upper_m2(self) -> float:
        """Upper bound [m^2]: the estimate plus two standard deviations (inf where nothing was measured)."""
        if not np.isfinite(self.sigma_m2):
            return float("inf")
        return max(self.area_m2, 0.0) + 2.0 * self.sigma_m2

    def to_dict(self) -> dict[str, object]:
        """JSON-ready summary (non-finite numbers as None)."""
        fields: dict[str, object] = {"area_m2": self.area_m2, "sigma_m2": self.sigma_m2, "pixels": self.pixels,
                                     "surfaces": self.surfaces, "method": self.method, "scans": self.scans,
                                  "albedos": "white" if self.white_surfaces else "measured"}
        out = {k: (v if not isinstance(v, float) or np.isfinite(v) else None) for k, v in fields.items()}
        out.update(significance=round(self.significance, 2), significant=self.significant)
        return out


NOTHING_MEASURED = FootprintEstimate(float("nan"), float("inf"), 0, 0)


def pool_estimates(estimates: list[FootprintEstimate]) -> FootprintEstimate:
    """One footprint from several scans' estimates: their inverse-variance mean (scans without one add nothing).

    (F14)  A = sum_s A_s / sigma_s^2 / sum_s sigma_s^-2,   sigma = (sum_s sigma_s^-2)^(-1/2)
    """
    usable = [e for e in estimates if np.isfinite(e.area_m2) and np.isfinite(e.sigma_m2) and e.sigma_m2 > 0]
    methods = tuple(sorted({m for e in estimates for m in e.methods})) or (EstimateMethod.PLANES,)
    pixels, surfaces = sum(e.pixels for e in estimates), sum(e.surfaces for e in estimates)
    if not usable:
        return FootprintEstimate(float("nan"), float("inf"), pixels, surfaces, methods, len(estimates))
    weights = np.array([e.sigma_m2**-2 for e in usable])
    area = float(np.sum(weights * [e.area_m2 for e in usable]) / weights.sum())
    return FootprintEstimate(area, float(weights.sum() ** -0.5), pixels, surfaces, methods, len(estimates))
