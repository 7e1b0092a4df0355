"""The first stage: what a scan says of its own sensor (:func:`read_sensor` -> :class:`SensorReading`).

- **The noise law**, measured from how much the scan's frequencies disagree
  (:func:`mpi_lidar.physics.noise_law.measure_noise_law`), in the scan's own amplitude unit: fusion, unwrapping,
  the consistency test, the no-return floor and the uncertainty use it, whatever the sensor's noise constant and
  unit. Where the scan has too few pixels for a significant law, the sensor's (a profile's noise scale included).
- **The amplitude unit**, which only the model's inputs and the radiometric limits need: the options' (a number, a
  sensor profile's), else V^2; either is checked against the scan's own evidence: surfaces far brighter than a
  white one at their range would be (a scanner's counts read as V^2), or a scan quieter at its darkest pixels
  than any sensor's no-light noise with nothing in it brighter than a dark surface (a unit far smaller than the
  one taken; dark alone is also a scene past the frequencies' combined ambiguity). Where the evidence contradicts
  the unit, the model is not applied. The scatter of the frequencies fixes only the product of the unit and the
  noise constant, so it is never read as a unit; only a bound on the noise no sensor passes is.
- **Saturation**, from the data: a plateau of clipped amplitudes at a frequency (several pixels at exactly its
  largest amplitude), or the options' threshold where a profile or the user gives one.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import cast

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.options import AUTO, CorrectionOptions
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.physics.noise_law import NoiseLaw, measure_noise_law
from mpi_lidar.scans.scan import Scan

# Pixels the law and the evidence are read from at most, evenly spaced over the scan.
SAMPLE_PIXELS = 20_000
# The unit is not V^2 where the brightest surfaces (the 99th percentile of amplitude x range^2 / Gamma_R, an albedo
# times the cosine of incidence in V^2) read above this (no surface reflects several times what a white one does).
MAX_BRIGHT_ALBEDO = 3.0
BRIGHT_PERCENTILE = 99.0
# Pixels read for that have a phase noise below this [rad] at every frequency.
CLEAR_PHASE_SIGMA_RAD = 0.15
# Nor where the scan is quieter than any sensor's front end: its noise at its darkest pixels (the law's quadrature
# sd at this percentile of the highest frequency's amplitudes, three of its relative errors up) below this share of
# the sensor model's no-light noise, while nothing in it is brighter than a dark surface (MAX_DARK_ALBEDO) or too
# few pixels stand clear to tell. Light only adds noise, so that noise bounds the scan's own no-light noise from
# above; a unit u moves it by u (and a dark scene by nothing), while a sensor's front end (its load's thermal noise,
# its amplifier's) is taken to be no more than ten times quieter than the model's.
DARK_PERCENTILE = 5.0
MIN_FLOOR_RATIO = 0.1
MAX_DARK_ALBEDO = 0.05
# Where too few pixels stand clear for the radiometry, a noise above this multiple of the sensor model's at the
# same amplitude contradicts the unit (a unit u moves it by u^(1/2) to u; a sensor's own noise differs by less).
MAX_NOISE_RATIO = 30.0
# A frequency's amplitudes have a saturation plateau where at least this many sampled pixels read its largest
# amplitude to this relative tolerance, and at least as many read less.
PLATEAU_PIXELS = 5
PLATEAU_TOLERANCE = 1e-6


@dataclass(frozen=True)
class SensorReading:
    """What a scan says of its sensor (:func:`read_sensor`).

    units_per_v2 : The scanner's unit per V^2 the amplitudes are divided by (1: V^2, given or assumed). [1 / V^2]
    unit_given : Whether the options (a number, a sensor profile) gave the unit; else V^2 is assumed.
    unit_contradiction : Why the scan's own evidence contradicts the unit taken ("" where nothing does).
    law : The scan's own noise law, in V^2 after the unit (None: not measured).
    noise : The noise model every later stage uses: the law's where it is significant, else the sensor's.
    saturation_v2 : The amplitude at or above which each frequency saturates (F,) [V^2] (inf: none).
    noise_over_reference : The scan's depth noise over the sensor model's (a profile's noise scale included) at the
        scan's median pixel, where the law was measured (NaN otherwise). [1]
    """

    units_per_v2: float
    unit_given: bool
    unit_contradiction: str
    law: NoiseLaw | None
    noise: NoiseModel
    saturation_v2: NDArray[np.float64]
    noise_over_reference: float = float("nan")

    @property
    def disagrees_with_reference(self) -> bool:
        """Whether the scan's own noise differs from the sensor model's (a profile's) beyond the law's uncertainty
        (three of its standard errors, and 10 % for the law's own shape)."""
        if self.law is None or not self.law.significant or not np.isfinite(self.noise_over_reference):
            return False
        return abs(self.noise_over_reference - 1.0) > 3 * self.law.relative_sigma / 2 + 0.1

    @property
    def unit_trusted(self) -> bool:
        """Whether the model may read the amplitudes: the unit given, or V^2 and nothing contradicts it."""
        return not self.unit_contradiction


def sensor_model(sensor: SensorConfig, scan: Scan, noise_scale: float = 1.0) -> NoiseModel:
    """The sensor's noise model for ``scan``: its frequencies, the speed of light it converted phases with, and
    ``noise_scale`` (a sensor profile's)."""
    reference = NoiseModel.for_sensor(sensor, scan.frequencies_hz, noise_scale)
    speed = float(getattr(scan, "speed_of_light_m_per_s", reference.speed_of_light_m_per_s))
    return replace(reference, speed_of_light_m_per_s=speed)


def read_sensor(scan: Scan, sensor: SensorConfig, options: CorrectionOptions) -> SensorReading:
    """The first stage of a scan's correction (the module's docstring)."""
    given = options.amplitude_scale != AUTO
    units = float(cast(float, options.amplitude_scale)) if given else 1.0
    reference = sensor_model(sensor, scan, options.noise_scale)
    rows = sample_rows(scan)
    f = len(scan.frequencies_hz)
    rows[:, f:] /= units
    if scan.depth_wrapped and rows.shape[0]:
        # The counts only: the law that would weigh the frequencies is not known yet.
        rows = reference.unwrap(rows, equal_amplitudes=True)[0].astype(np.float64)
    law = measure_noise_law(rows, reference) if rows.shape[0] else None
    noise = law.model(reference) if law is not None and law.significant else reference
    ratio = _noise_ratio(rows, f, noise, reference) if noise is not reference else float("nan")
    floor = _floor_ratio(rows, f, law, noise, reference) if noise is not reference else float("nan")
    contradiction = _unit_evidence(rows, f, sensor, noise, ratio, floor)
    if contradiction and given:
        contradiction = f"with the unit given ({units:g} per V^2), {contradiction}"
    return SensorReading(units, given, contradiction, law, noise, _saturation_v2(rows, f, options), ratio)


def _noise_ratio(rows: NDArray, f: int, noise: NoiseModel, reference: NoiseModel) -> float:
    """The depth noise of ``noise`` over that of ``reference`` at the rows' median amplitudes (the highest
    frequency's). [1]"""
    with np.errstate(invalid="ignore"):
        amplitude = np.nanmedian(np.where(rows[:, f:] > 0, rows[:, f:], np.nan), axis=0)[None, :]
    if not np.isfinite(amplitude).all():
        return float("nan")
    return float(noise.depth_sigma_m(amplitude)[0, -1] / reference.depth_sigma_m(amplitude)[0, -1])


def sample_rows(scan: Scan) -> NDArray[np.float64]:
    """Raw rows (n, 2F) of at most ``SAMPLE_PIXELS`` pixels evenly spaced over the scan, in float64, amplitudes in
    the scan's unit."""
    h, w = scan.shape
    pixels = np.unique(np.linspace(0, h * w - 1, min(SAMPLE_PIXELS, h * w)).round().astype(np.intp))
    y, x = np.divmod(pixels, w)
    depth = np.asarray(scan.depth[:, y, x], dtype=np.float64).T
    amplitude = np.asarray(scan.amplitude[:, y, x], dtype=np.float64).T
    return np.hstack([depth, amplitude])


def _floor_ratio(rows: NDArray, f: int, law: NoiseLaw | None, noise: NoiseModel, reference: NoiseModel) -> float:
    """The most the scan's no-light noise can be, over the sensor model's: the law's quadrature sd at the darkest
    pixels (``DARK_PERCENTILE`` of the highest frequency's amplitudes), three of its relative errors up, over the
    model's no-light sd. [1]"""
    amplitude = rows[:, 2 * f - 1]
    amplitude = amplitude[np.isfinite(amplitude) & (amplitude > 0)]
    if law is None or amplitude.size == 0 or not reference.floor_v2[-1] > 0:
        return float("nan")
    dark = np.full((1, f), float(np.percentile(amplitude, DARK_PERCENTILE)))
    sigma = float(noise.quadrature_sigma_v2(dark)[0, -1]) * np.sqrt(1 + 3 * law.relative_sigma)
    return sigma / float(reference.floor_v2[-1])


def _unit_evidence(rows: NDArray, f: int, sensor: SensorConfig, noise: NoiseModel, ratio: float,
                   floor: float) -> str:
    """Why the rows' amplitudes (in V^2 after the unit taken) cannot be in V^2, or "" where nothing says so.

    ``ratio`` is the scan's depth noise over the sensor model's at the same amplitude, ``floor`` the most its
    no-light noise can be over the model's (:func:`_floor_ratio`; NaN: no law measured). Only pixels whose light
    stands well above their noise are read for the radiometry (a noisy amplitude times a far range squared reads as
    a bright surface). Too bright settles a larger unit; where too few pixels stand clear, a noise far above any
    sensor's does. Too dark alone does not settle a smaller one (a scene past the frequencies' combined ambiguity
    reads dark too): it needs a scan quieter at its darkest pixels than any sensor's no-light noise.
    """
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        clear = (noise.quadrature_sigma_v2(rows[:, f:]) / rows[:, f:] < CLEAR_PHASE_SIGMA_RAD).all(1)
        albedo = rows[:, 2 * f - 1] * rows[:, f - 1] ** 2 / sensor.gamma_r_v2
        albedo = albedo[clear & np.isfinite(albedo) & (rows[:, f - 1] > 0)]
    bright = float(np.percentile(albedo, BRIGHT_PERCENTILE)) if albedo.size >= 20 else float("nan")
    if bright > MAX_BRIGHT_ALBEDO:
        return (f"its brightest surfaces would reflect {bright:.3g} times what a white one does at their range: the "
                "amplitudes are in another unit")
    if np.isnan(bright) and ratio > MAX_NOISE_RATIO:
        return f"its noise is {ratio:.3g} times the sensor's at the same amplitude: the amplitudes are in another unit"
    if floor < MIN_FLOOR_RATIO and not bright >= MAX_DARK_ALBEDO:
        seen = ("too few of its pixels stand clear of their noise to read their brightness" if np.isnan(bright) else
                f"its brightest surfaces would reflect only {bright:.2g} of what a white one does at their range")
        return (f"its noise at its darkest pixels is only {floor:.2g} of the sensor's no-light noise, quieter than any "
                f"sensor's, and {seen}: the amplitudes are in a unit far smaller than V^2")
    return ""


def _saturation_v2(rows: NDArray, f: int, options: CorrectionOptions) -> NDArray[np.float64]:
    """Each frequency's saturation amplitude (F,) [V^2]: a plateau at its largest sampled amplitude, else the
    options' threshold, else none (inf)."""
    given = np.inf if options.saturation_amplitude_v2 is None else float(options.saturation_amplitude_v2)
    levels = np.full(f, given)
    for column in range(f):
        amplitude = rows[:, f + column]
        amplitude = amplitude[np.isfinite(amplitude)]
        if amplitude.size == 0:
            continue
        top = float(amplitude.max())
        at_top = int((amplitude >= top * (1 - PLATEAU_TOLERANCE)).sum())
        # Clipping cuts the bright end off a spread of amplitudes; a scan all of one amplitude has no plateau to tell.
        below = amplitude.size - at_top
        if top > 0 and at_top >= PLATEAU_PIXELS and below >= PLATEAU_PIXELS:
            levels[column] = min(levels[column], top * (1 - PLATEAU_TOLERANCE))
    return levels
