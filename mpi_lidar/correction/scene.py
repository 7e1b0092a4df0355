"""The scene-geometry stage: what the scan's own geometry says about multipath, worked out once per scan.

A scan passes validity -> scene geometry -> model -> outputs. This stage takes the highest-frequency depth of the
usable pixels and, where the scan has rays: fits the facing blocks (:func:`mpi_lidar.scans.geometry.facing_blocks`),
measures the scan's own receiver footprint where ``footprint_area_m2`` is "auto"
(:func:`mpi_lidar.correction.footprint.estimate_footprint`), the expected multipath bias of every pixel at that
footprint (the facing blocks', and the partner planes' where the blocks do not reach the gate), and, for a
geometric model, its per-pixel inputs. Gates (:mod:`mpi_lidar.correction.gates`) decide
from the result, :class:`SceneGeometry`; ``mpi-lidar calibrate`` and the benchmarks use the same functions.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.footprint import (
    FootprintEstimate,
    PlaneModelInputs,
    SurfaceLabels,
    block_albedo,
    estimate_footprint,
    plane_model_inputs,
    surface_labels,
    unbent_planes,
    white_albedo,
)
from mpi_lidar.correction.options import AUTO, MAX_FOOTPRINT_AREA_M2, CorrectionOptions, GateName
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.scans import geometry
from mpi_lidar.scans.scan import Scan
from mpi_lidar.threads import on_cores

NO_GEOMETRY_NOTE = "no scan geometry: the geometry gate fell back to pixel-wise correction of every valid pixel"
NO_GEOMETRY_INPUTS_NOTE = ("no scan geometry: the model needs geometric inputs (rho_ABA, d_AB), so it corrects no "
                           "pixel; every valid pixel gets the baseline")
# The footprint a coarse scan measures on finer blocks strays further from the truth than its sd says: estimate /
# truth over the half-size rooms of the corner-strength benchmark, rendered by the project and path traced, read
# 0.68-1.38x (26 % rms in log, docs/results/path-traced.md); a corrected depth's uncertainty carries that share.
FINER_BLOCKS_SYSTEMATIC_SHARE = 0.26
# Pixels whose partner-plane bias is worked out at once: the sums over their partners' patches take about a
# kilobyte a pixel while they are made (as the model's inputs do).
PLANE_BIAS_PIXELS = 16_384


@dataclass(frozen=True)
class SceneGeometry:
    """What the scene-geometry stage found in one scan (:func:`analyse_geometry`).

    Every field but ``notes`` is None for a scan without geometry (no rays or scan grid).

    Attributes
    ----------
    blocks : geometry.FacingBlocks | None
        The scan's blocks, their planes and facing pairs.
    surfaces : SurfaceLabels | None
        The blocks' connected and flat surfaces, where some blocks face each other.
    footprint : FootprintEstimate | None
        The scan's own footprint estimate where ``footprint_area_m2`` is "auto"; None where it was given.
    footprint_m2 : float
        The footprint A_fp the potential, the bias map and the model's inputs are for: the given one, the
        scan's own estimate where significant, else 0 (no multipath). [m^2]
    potential : geometry.BlockPotential | None
        The expected multipath per block at ``footprint_m2`` (pixels interpolate it).
    bias_m : NDArray[np.float32] | None
        Expected multipath bias per pixel (H, W) at ``footprint_m2``: the facing blocks' and, where that does not
        reach ``CorrectionOptions.min_multipath_bias_m``, the partner planes' where larger in size
        (:meth:`PlaneModelInputs.bias_m`: the light of surfaces beyond the view or the partner range). [m]
    reaches_min_bias : NDArray[np.bool_] | None
        Bool (H*W,): where ``bias_m`` reaches ``CorrectionOptions.min_multipath_bias_m`` in size.
    uncalibrated : NDArray[np.bool_] | None
        Bool (H*W,), only where the scan's own estimate is not significant: the pixels whose bias could reach
        ``min_multipath_bias_m`` at the estimate's upper bound (they are left as measured).
    left_alone_potential : geometry.BlockPotential | None
        Where the scan measured its own footprint: the facing blocks' multipath for the uncertainty of a depth
        left alone, at :func:`uncertainty_footprint_m2` (where the estimate is not significant, the footprint's
        root mean square under its uncertainty) with each partner weighed by its measured albedo (``bias_m`` is the
        gate's: white partners, the most the geometry allows). :meth:`left_alone_bias_m` reads it; the gate
        does not.
    model_inputs : PlaneModelInputs | None
        A geometric model's per-pixel inputs (rho_ABA, d_AB) at ``footprint_m2``; None unless asked for.
    notes : tuple[str, ...]
        What a report must say of the scene (a scan without geometry under the geometry gate or a geometric model).
    """

    blocks: geometry.FacingBlocks | None = None
    surfaces: SurfaceLabels | None = None
    footprint: FootprintEstimate | None = None
    footprint_m2: float = 0.0
    potential: geometry.BlockPotential | None = None
    bias_m: NDArray[np.float32] | None = None
    reaches_min_bias: NDArray[np.bool_] | None = None
    uncalibrated: NDArray[np.bool_] | None = None
    model_inputs: PlaneModelInputs | None = None
    notes: tuple[str, ...] = ()
    left_alone_potential: geometry.BlockPotential | None = None

    def left_alone_bias_m(self, pixels: NDArray) -> NDArray[np.float64]:
        """The multipath bias (n,) [m] a depth left alone carries in its uncertainty, at flat pixel indices (n,):
        where the facing blocks set ``bias_m``, theirs from ``left_alone_potential``; where the partner planes
        set it (larger than the blocks'; they weigh the albedos already), ``bias_m``. Worked out per call from the
        blocks, so no map of the whole scan is kept for it."""
        assert self.bias_m is not None, "a scan with geometry"
        bias = self.bias_m.reshape(-1)[pixels].astype(np.float64)
        if self.left_alone_potential is None or self.potential is None:
            return bias
        white = self.potential.pixels(pixels).bias_m
        # The planes replace the blocks' bias only where larger; a relative margin absorbs float32 storage.
        from_blocks = np.abs(bias) <= np.abs(white) * (1 + 1e-5) + 1e-12
        return np.where(from_blocks, self.left_alone_potential.pixels(pixels).bias_m, bias)

    @property
    def has_geometry(self) -> bool:
        """Whether the scan had rays, so that its geometry could be analysed."""
        return self.blocks is not None


def scene_blocks(scan: Scan, usable_depth: NDArray, options: CorrectionOptions, noise: NoiseModel | None = None,
                 block_pixels: int | None = None) -> geometry.FacingBlocks | None:
    """The scan's facing blocks from the highest-frequency depth of its usable pixels ``usable_depth`` (H*W,) [m]
    (NaN elsewhere), in tiles of ``options.tile_pixels``, their planes judged against that depth's noise under
    ``noise`` (None: against their own residuals); None for a scan without geometry. ``block_pixels``: the
    blocks' side [px] (None: about ``options.geometry_block_m``)."""
    rays = scan.ray_rows()
    if rays is None:
        return None
    sigma = None if noise is None else depth_sigma_map(scan, usable_depth, noise, options.tile_pixels)
    return geometry.facing_blocks(usable_depth.reshape(scan.shape), rays, block_m=options.geometry_block_m,
                                  max_range_m=options.partner_range_m, band_pixels=options.tile_pixels,
                                  depth_sigma=sigma, block_pixels=block_pixels)


def finer_scene_blocks(scan: Scan, usable_depth: NDArray, options: CorrectionOptions, noise: NoiseModel | None,
                       blocks: geometry.FacingBlocks) -> geometry.FacingBlocks | None:
    """:func:`scene_blocks` on a finer grid than ``blocks`` where the scan is coarse
    (:func:`~mpi_lidar.scans.geometry.finer_block_pixels`) and some of the finer blocks face each other; None
    elsewhere.

    A footprint fit that settles nowhere on a coarse scan's blocks is measured again on these: a room seen in
    a few dozen pixels is a handful of blocks a surface, most of them along its folds, and the fit has too little
    of each surface left to measure on (at 24 x 32 pixels no room of the corner-strength benchmark measured its
    footprint on blocks of 4 x 4 pixels, every one on blocks of 2 x 2)."""
    rays = scan.ray_rows()
    if rays is None:
        return None
    finer = geometry.finer_block_pixels(usable_depth.reshape(scan.shape), rays, options.geometry_block_m)
    if finer is None or finer >= blocks.block_pixels:
        return None
    found = scene_blocks(scan, usable_depth, options, noise, block_pixels=finer)
    return found if found is not None and found.pairs.a.size else None


def depth_sigma_map(scan: Scan, usable_depth: NDArray, noise: NoiseModel, tile_pixels: int) -> NDArray[np.float32]:
    """The sd (H, W) [m] of the highest-frequency depth (the one ``usable_depth`` (H*W,) holds) at each pixel's
    amplitude under ``noise``, NaN where the depth is not usable; a band of rows at a time."""
    h, w = scan.shape
    highest = len(scan.frequencies_hz) - 1
    # The highest frequency's law alone: the other frequencies' sds would be worked out only to be dropped.
    law = dataclasses.replace(noise, frequencies_hz=noise.frequencies_hz[highest:],
                              read_variance_v4=noise.read_variance_v4[highest:],
                              shot_variance_v2=noise.shot_variance_v2[highest:])
    sigma = np.full((h, w), np.nan, dtype=np.float32)
    usable = np.isfinite(usable_depth).reshape(h, w)
    step = max(1, tile_pixels // max(w, 1))
    for top in range(0, h, step):
        rows = slice(top, min(top + step, h))
        amplitude = np.asarray(scan.amplitude[highest, rows], dtype=np.float64).reshape(-1, 1)
        band = law.depth_sigma_m(amplitude).reshape(-1, w)
        sigma[rows] = np.where(usable[rows], band, np.nan)
    return sigma


def analyse_geometry(scan: Scan, usable_depth: NDArray, options: CorrectionOptions, sensor: SensorConfig, *,
                     with_model_inputs: bool = False, noise: NoiseModel | None = None,
                     unit_trusted: bool = True) -> SceneGeometry:
    """The scene-geometry stage of one scan.

    Parameters
    ----------
    scan : Scan
        The scan (its maps may stay in the store).
    usable_depth : NDArray
        Highest-frequency depth (H*W,) of the usable pixels, NaN elsewhere (:func:`validity.usable_depth`). [m]
        Read only here: the caller may overwrite it afterwards.
    options : CorrectionOptions
        Block size, partner range, footprint ("auto": the scan's own), the bias threshold and the tile size.
    sensor : SensorConfig
        The sensor (noise model, Gamma_R) the footprint fit needs.
    with_model_inputs : bool
        Also hand on a geometric model's per-pixel inputs (:attr:`SceneGeometry.model_inputs`). The bias map and
        the gate's pixels do not depend on it: the partner planes are worked out wherever blocks face each other
        and the footprint is above zero.
    noise : NoiseModel | None
        The scan's noise model, which sets how far noise can turn the block planes and weighs the footprint fit
        (None: the sensor's, scaled by ``options.noise_scale``).
    unit_trusted : bool
        Whether the amplitudes are in V^2 (:attr:`SensorReading.unit_trusted`). Where not, no albedo is read from
        them: the footprint is measured and the bias worked out with white surfaces
        (:func:`estimate_footprint`'s ``white_partners``), so the estimate is the footprint times the albedos the
        light returns from and the bias a depth left alone carries is the scan's own.

    Returns
    -------
    SceneGeometry
        What the scan's geometry says; for a scan without geometry, only its notes.
    """
    noise = noise or NoiseModel.for_sensor(sensor, scan.frequencies_hz, options.noise_scale)
    blocks = scene_blocks(scan, usable_depth, options, noise)
    if blocks is None:
        if with_model_inputs:
            return SceneGeometry(notes=(NO_GEOMETRY_INPUTS_NOTE,))
        return SceneGeometry(notes=(NO_GEOMETRY_NOTE,) if options.gate == GateName.GEOMETRY else ())
    auto = options.footprint_area_m2 == AUTO
    estimate, uncalibrated, measured_albedo = None, None, None

    def albedos(of: geometry.FacingBlocks) -> NDArray[np.float64]:
        """The blocks' albedos from the amplitudes, or white where their unit is not trusted."""
        return block_albedo(scan, of, sensor, options.tile_pixels) if unit_trusted else white_albedo(of)

    def measured_on(of: geometry.FacingBlocks) -> tuple[FootprintEstimate, NDArray[np.float64], SurfaceLabels | None]:
        """The footprint estimate on the blocks ``of``, their albedos and surfaces."""
        albedo, labels = albedos(of), surface_labels(of) if of.pairs.a.size else None
        found = estimate_footprint(scan, of, np.isfinite(usable_depth), sensor, noise=noise, measured_albedo=albedo,
                                   surfaces=labels, white_partners=not unit_trusted)
        return found, albedo, labels

    if not auto:
        # Validated options hold a number here; no float() of it, so a bad value fails where it is used.
        footprint_m2 = cast(float, options.footprint_area_m2)
        finer = finer_scene_blocks(scan, usable_depth, options, noise, blocks)
        if finer is not None:  # no fit to settle: a coarse scan's surfaces are resolved better on finer blocks
            blocks = finer
        surfaces = surface_labels(blocks) if blocks.pairs.a.size else None
        potential = blocks.block_potential(footprint_m2)
    else:
        estimate, measured_albedo, surfaces = measured_on(blocks)
        finer = finer_scene_blocks(scan, usable_depth, options, noise, blocks) if settled_nowhere(estimate) else None
        if finer is not None:
            on_finer = measured_on(finer)
            if np.isfinite(on_finer[0].sigma_m2):  # it settled: its bound, significant or not, not the cap
                blocks, (estimate, measured_albedo, surfaces) = finer, on_finer
                estimate = dataclasses.replace(estimate, systematic_share=FINER_BLOCKS_SYSTEMATIC_SHARE)
        if estimate.significant:
            footprint_m2 = estimate.area_m2
        else:
            upper = blocks.block_potential(min(estimate.upper_m2(), MAX_FOOTPRINT_AREA_M2))
            uncalibrated = _reaches_min_bias(upper, options)
            footprint_m2 = 0.0
        potential = blocks.block_potential(footprint_m2)
    bias_m = np.empty(scan.shape, dtype=np.float32)
    reaches = _reaches_min_bias(potential, options, bias_m)
    inputs = None
    if with_model_inputs or (surfaces is not None and footprint_m2 > 0):
        planes = None
        if surfaces is not None and footprint_m2 > 0:
            if measured_albedo is None:
                measured_albedo = albedos(blocks)
            planes = unbent_planes(scan, blocks, np.isfinite(usable_depth), sensor, footprint_m2, surfaces=surfaces,
                                   measured_albedo=measured_albedo, white_surfaces=not unit_trusted, noise=noise)
        inputs = plane_model_inputs(scan, blocks, sensor, footprint_m2, surfaces, measured_albedo, options.tile_pixels,
                                    white_surfaces=not unit_trusted, fitted_planes=planes)
        _add_plane_bias(inputs, blocks, usable_depth, max(scan.frequencies_hz), options, bias_m, reaches)
    # No partner returns more than a white one: a block read above 1 (its own multipath's gain) counts as white.
    left_alone = (None if estimate is None or measured_albedo is None
                  else blocks.block_potential(uncertainty_footprint_m2(estimate), np.minimum(measured_albedo, 1.0)))
    return SceneGeometry(blocks, surfaces, estimate, footprint_m2, potential, bias_m, reaches, uncalibrated,
                         inputs if with_model_inputs else None, left_alone_potential=left_alone)


def settled_nowhere(estimate: FootprintEstimate) -> bool:
    """Whether a footprint fit on facing surfaces settled nowhere (an infinite sd): what sends a coarse scan's fit to
    finer blocks. An estimate that settled, significant or not, is the scan's answer: trying other blocks until
    one is significant would find multipath where there is none."""
    return estimate.pixels > 0 and not np.isfinite(estimate.sigma_m2)


def uncertainty_footprint_m2(estimate: FootprintEstimate) -> float:
    """The footprint [m^2] whose multipath the uncertainty of a depth left alone carries: a significant estimate's
    own, else :func:`rms_footprint_m2`."""
    return estimate.area_m2 if estimate.significant else rms_footprint_m2(estimate)


def rms_footprint_m2(estimate: FootprintEstimate) -> float:
    """The footprint [m^2] whose bias stands for a scan's multipath where its own estimate is not significant: the
    root mean square of the footprint under the estimate's uncertainty, hypot(estimate, sd) (the bias grows about
    as the footprint, so its mean square is the bias at this footprint's, squared), capped at
    :data:`~mpi_lidar.correction.options.MAX_FOOTPRINT_AREA_M2` (as the estimate's upper bound for the pixels
    left uncalibrated). A fit that settled nowhere on facing surfaces (sd infinite) bounds nothing below the cap,
    so the cap it is; 0 where nothing was measured (no facing surfaces to tell it: the scan then says nothing of
    its multipath)."""
    if estimate.pixels == 0:
        return 0.0
    if not np.isfinite(estimate.sigma_m2):
        return MAX_FOOTPRINT_AREA_M2
    area = max(float(estimate.area_m2), 0.0) if np.isfinite(estimate.area_m2) else 0.0
    return min(float(np.hypot(area, float(estimate.sigma_m2))), MAX_FOOTPRINT_AREA_M2)


def _reaches_min_bias(potential: geometry.BlockPotential, options: CorrectionOptions,
                      bias_out: NDArray | None = None) -> NDArray[np.bool_]:
    """Where the bias reaches ``options.min_multipath_bias_m`` (H*W,), a band of rows at a time; the bias [m] goes
    into ``bias_out`` (H, W) where given."""
    reaches = np.empty(potential.blocks.shape, dtype=bool)

    def band(rows: slice) -> None:
        bias = potential.bias_rows(rows)
        reaches[rows] = bias >= options.min_multipath_bias_m
        if bias_out is not None:
            bias_out[rows] = bias

    on_cores(band, potential.blocks.bands(options.tile_pixels))
    return reaches.ravel()


def _add_plane_bias(inputs: PlaneModelInputs, blocks: geometry.FacingBlocks, usable_depth: NDArray,
                    frequency_hz: float, options: CorrectionOptions, bias_out: NDArray, reaches: NDArray) -> None:
    """Where the partner planes predict a larger bias than the blocks (:meth:`PlaneModelInputs.bias_m` at
    ``frequency_hz`` [Hz], the highest), it replaces the blocks' in ``bias_out`` (H, W) [m] and reaches the gate in
    ``reaches`` (H*W,) where at least ``options.min_multipath_bias_m`` in size; a band of rows at a time.

    The blocks see only the block pairs that face each other within the partner range and in view; a room's
    far wall, floor or ceiling lights a pixel from beyond either, and the planes continue the surfaces there. A
    scan without partner planes keeps the blocks' bias to the bit."""
    if inputs.plane is None:
        return
    width = blocks.shape[1]
    flat_bias = bias_out.reshape(-1)

    def band(rows: slice) -> None:
        pixels = np.arange(rows.start * width, rows.stop * width)
        pixels = pixels[np.isfinite(usable_depth[pixels]) & ~reaches[pixels]]
        for start in range(0, pixels.size, PLANE_BIAS_PIXELS):
            chunk = pixels[start:start + PLANE_BIAS_PIXELS]
            plane = inputs.bias_m(chunk, usable_depth[chunk].astype(np.float64), frequency_hz)
            larger = np.abs(plane) > flat_bias[chunk]
            flat_bias[chunk[larger]] = plane[larger]
            reaches[chunk] |= np.abs(plane) >= options.min_multipath_bias_m

    on_cores(band, blocks.bands(options.tile_pixels))
