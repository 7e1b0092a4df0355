"""Scenes rendered by an independent path tracer: Mitsuba 3 with mitransient, one transient render per pixel.

The project's renderer (:mod:`mpi_lidar.simulation.scenes`) integrates its own light-transport kernel over patches,
the same kernel the correction's geometry stage models. This module renders the same scene geometry with a
general-purpose Monte Carlo path tracer instead, so a check of correction on its scans does not share the
kernel's assumptions (patch sizes, the cap at strong coupling, the bounce count, occlusion).

The coaxial scanner is modelled by reciprocity. A real scanner lights a small spot A and its receiver collects
what comes back from a footprint of area A_fp around it; the multipath is the light A scatters to the other
surfaces that they return into the footprint. Swapping source and receiver gives the same transport: a receiver
that sees only along the pixel's ray (a pinhole camera with a 1 x 1 film and a field of view of 0.01 degrees) and a
uniform spot light at the scanner whose cone has the cross-section A_fp at the pixel's range. A path from the
camera reaches A, and from there the light of the beam directly (the direct return) or through other surfaces
(the multipath), up to ``max_depth`` segments. The film records the radiance per optical path length (a
histogram, bins of ``BIN_OPL_M``), which becomes the correlation phasor sum_t h(t) e^{j 4 pi f (opl / 2) / c}.

Units: a white Lambertian plane square on at 1 m returns the radiance I / pi of a spot of intensity I, and the
sensor's amplitude Gamma_R there (eq F3 of the footprint docs), so the amplitude is pi Gamma_R / I times the
radiance; no figure of the scene enters the scale.

Needs the ``render`` dependency group (mitsuba, mitransient: ``make test`` builds .venv with it) and an LLVM of
version 19 or later for Dr.Jit's CPU backend (``make system-deps`` installs Debian's libllvm19);
:func:`llvm_library` finds it.
"""

from __future__ import annotations

import glob
import os
import re
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config
from mpi_lidar.scans.scan import Scan, grid_rays
from mpi_lidar.simulation.scenes import Rectangle, Scene, first_hits, scan_from_phasors, simple_region_mask

# Histogram bins of optical path length [m]: a path is taken at its bin's centre, off by at most half a bin (a
# quarter in depth, 0.05 mm; the film's window is one for the whole scene, so the bins cannot be centred on each
# pixel's direct return).
BIN_OPL_M = 2e-4
# Optical path beyond the farthest direct return [m] the histogram keeps: in a room of 2.2 m each bounce adds a
# metre or more and keeps at most the albedo of the light, so the paths past it carry well under 1 % of it.
WINDOW_OPL_M = 8.0
# The camera's field of view [deg]: its ray spreads 0.17 mm at 2 m, so the direct path is 2 d to 1e-8 m.
CAMERA_FOV_DEG = 0.01
# Mitsuba's camera rays start this far from the camera [m] and mitransient counts their length from there: added
# back to every path (the camera's field of view is so narrow that every ray starts it straight ahead).
NEAR_CLIP_M = 1e-3
SPOT_INTENSITY = 1.0
# Segments of a path at most: camera -> A, then up to nine bounces before the light.
DEFAULT_MAX_DEPTH = 10
DEFAULT_SAMPLES = 16384
MIN_LLVM_VERSION = 19
LLVM_GLOBS = ("/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/llvm-*/lib/libLLVM*.so*")


SYNC_RENDER_GROUP = "run .venv/bin/uv sync --frozen (the default groups hold the render group)"


class RendererMissingError(RuntimeError):
    """Mitsuba, mitransient or a recent enough LLVM is not installed."""


def llvm_library() -> str | None:
    """The path of an LLVM 19+ shared library for Dr.Jit's CPU backend (``DRJIT_LIBLLVM_PATH`` where set), or None.

    Dr.Jit 1.x emits instructions LLVM 15 and earlier cannot select (its kernels fail to compile there), and it
    looks for libLLVM.so by default, which Debian names by version."""
    given = os.environ.get("DRJIT_LIBLLVM_PATH")
    if given:
        return given
    versions = {}
    for path in {path for pattern in LLVM_GLOBS for path in glob.glob(pattern)}:
        match = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path))
        if match and int(match.group(1)) >= MIN_LLVM_VERSION:
            versions[path] = int(match.group(1))
    return max(versions, key=lambda path: (versions[path], path)) if versions else None


def _mitsuba() -> Any:
    """Mitsuba on its monochromatic CPU variant, with mitransient's plugins registered."""
    library = llvm_library()
    if library is None:
        raise RendererMissingError("no LLVM 19+ library found for Mitsuba's CPU backend: run make system-deps "
                                   "as root (it installs libllvm19) or set DRJIT_LIBLLVM_PATH")
    os.environ.setdefault("DRJIT_LIBLLVM_PATH", library)
    try:
        import mitsuba as mi
    except ImportError as error:
        raise RendererMissingError(f"mitsuba is not installed: {SYNC_RENDER_GROUP}") from error
    mi.set_variant("llvm_ad_mono")
    try:
        import mitransient  # noqa: F401  (registers the transient film and integrator)
    except ImportError as error:
        raise RendererMissingError(f"mitransient is not installed: {SYNC_RENDER_GROUP}") from error
    return mi


@dataclass(frozen=True)
class PathTraced:
    """One scene path traced: the correlation phasors (F, H, W) [V^2] with all the light and with the direct
    return alone, and the sum of the light (H, W) [V^2] (the phasors' DC part)."""

    phasor: NDArray[np.complex128]
    direct: NDArray[np.complex128]
    light: NDArray[np.float64]


def path_trace(scene: Scene, config: Config, footprint_m2: float, *, samples: int = DEFAULT_SAMPLES,
               max_depth: int = DEFAULT_MAX_DEPTH, seed: int = 0) -> PathTraced:
    """Render every pixel of ``scene`` (rectangles only) with Mitsuba: a spot light of cross-section
    ``footprint_m2`` [m^2] at the pixel's range and a camera along its ray, ``samples`` paths per pixel of up to
    ``max_depth`` segments, and again with the direct return alone (two segments)."""
    mi = _mitsuba()
    rays = grid_rays(scene.azimuth_rad, scene.elevation_rad).reshape(-1, 3)
    ranges, _ = first_hits(scene)
    frequencies = np.asarray(config.frequencies_hz, dtype=np.float64)
    c = config.sensor.speed_of_light_m_per_s
    scale = np.pi * config.sensor.gamma_r_v2 / SPOT_INTENSITY
    hit = np.isfinite(ranges)
    if not hit.any():
        raise ValueError(f"path_trace: no ray of {scene.name} meets a surface; nothing to render")
    start = 2 * float(ranges[hit].min()) - 0.01
    bins = int(np.ceil((2 * float(ranges[hit].max()) + WINDOW_OPL_M - start) / BIN_OPL_M))
    opl = start + (np.arange(bins) + 0.5) * BIN_OPL_M + NEAR_CLIP_M
    # e^{+j 2 pi f t}, t = opl / c: the phasor convention of mpi_lidar.physics.transport
    kernel = np.exp(2j * np.pi * np.outer(frequencies, opl) / c)
    f = frequencies.size
    out = {depth: np.zeros((rays.shape[0], f), dtype=np.complex128) for depth in (max_depth, 2)}
    light = np.zeros(rays.shape[0])
    for depth in (max_depth, 2):
        scene_mi = mi.load_dict(_scene_dict(mi, scene, depth, start, bins))
        params = mi.traverse(scene_mi)
        for pixel in np.flatnonzero(hit):
            d = float(ranges[pixel])
            frame = _look_along(mi, rays[pixel])
            params["sensor.to_world"] = frame
            params["light.to_world"] = frame
            angle = float(np.degrees(np.arctan(np.sqrt(footprint_m2 / np.pi) / d)))
            params["light.cutoff_angle"] = angle
            params["light.beam_width"] = angle
            params.update()
            _, transient = mi.render(scene_mi, spp=samples, seed=int(seed + pixel))
            histogram = scale * np.asarray(transient, dtype=np.float64).reshape(-1)
            out[depth][pixel] = kernel @ histogram
            if depth == max_depth:
                light[pixel] = histogram.sum()
    h, w = scene.elevation_rad.size, scene.azimuth_rad.size
    return PathTraced(out[max_depth].T.reshape(f, h, w), out[2].T.reshape(f, h, w), light.reshape(h, w))


def scan_of(scene: Scene, traced: PathTraced, config: Config, rng: np.random.Generator, *,
            direct_only: bool = False) -> Scan:
    """The scan of a path-traced scene through the sensor model (Table I noise from ``rng``), with the scene's
    exact reference depth and mask; of the direct return alone where ``direct_only``."""
    h, w = scene.elevation_rad.size, scene.azimuth_rad.size
    ranges, which = first_hits(scene)
    reference = np.where(np.isfinite(ranges), ranges, np.nan).reshape(h, w).astype(np.float32)
    phasor = traced.direct if direct_only else traced.phasor
    light = np.abs(traced.direct) if direct_only else np.broadcast_to(traced.light, phasor.shape)
    # A pixel the beam misses returns nothing: its phasor is zero and the sensor reads noise there.
    return scan_from_phasors(f"{scene.name} (path traced)", phasor, config, rng, dc_gamma=light,
                             azimuth_rad=scene.azimuth_rad, elevation_rad=scene.elevation_rad,
                             reference_depth=reference, reference_mask=simple_region_mask(scene, which.reshape(h, w)))


def true_bias_m(traced: PathTraced, config: Config) -> NDArray[np.float64]:
    """The multipath bias of the highest frequency's noise-free depth (H, W) [m]: the phase of all the light
    against the direct return's."""
    f = config.frequencies_hz[-1]
    ratio = traced.phasor[-1] / np.where(traced.direct[-1] == 0, np.nan, traced.direct[-1])
    return np.angle(ratio) * config.sensor.speed_of_light_m_per_s / (4 * np.pi * f)


def _scene_dict(mi: Any, scene: Scene, max_depth: int, start_opl_m: float, bins: int) -> dict[str, Any]:
    """Mitsuba's description of ``scene``: its rectangles as diffuse shapes, a spot light and a one-pixel transient
    camera at the origin (both moved per pixel) whose film keeps ``bins`` bins from ``start_opl_m`` [m] on."""
    found: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "transient_path", "max_depth": max_depth, "temporal_filter": "box"},
        "light": {"type": "spot", "intensity": {"type": "spectrum", "value": SPOT_INTENSITY}, "cutoff_angle": 1.0,
                  "beam_width": 1.0},
        "sensor": {"type": "perspective", "fov": CAMERA_FOV_DEG, "near_clip": NEAR_CLIP_M,
                   "film": {"type": "transient_hdr_film", "width": 1, "height": 1, "temporal_bins": bins,
                            "start_opl": start_opl_m, "bin_width_opl": BIN_OPL_M, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 1}},
    }
    for index, surface in enumerate(scene.surfaces):
        if not isinstance(surface, Rectangle):
            raise ValueError(f"path_trace: surface {index} of {scene.name} is a {type(surface).__name__}; "
                             "only rectangles are handed to Mitsuba")
        found[f"surface_{index}"] = _rectangle(mi, surface)
    return found


def _rectangle(mi: Any, surface: Rectangle) -> dict[str, Any]:
    """A Mitsuba rectangle ([-1, 1]^2 in its frame, normal +z) on ``surface``: its half extents as the frame's
    first two axes and its normal half_u x half_v as the third; one-sided faces reflect on that side only."""
    centre, half_u, half_v = (np.asarray(v, dtype=np.float64) for v in (surface.centre, surface.half_u,
                                                                        surface.half_v))
    normal = np.cross(half_u, half_v)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = half_u, half_v, normal / np.linalg.norm(normal), centre
    diffuse = {"type": "diffuse", "reflectance": {"type": "spectrum", "value": float(surface.albedo)}}
    bsdf = {"type": "twosided", "material": diffuse} if surface.two_sided else diffuse
    return {"type": "rectangle", "to_world": mi.ScalarTransform4f(matrix.tolist()), "bsdf": bsdf}


def _look_along(mi: Any, ray: NDArray) -> Any:
    """The frame at the origin whose +z is ``ray`` (unit (3,))."""
    up = [0.0, 1.0, 0.0] if abs(ray[1]) < 0.9 else [1.0, 0.0, 0.0]
    return mi.ScalarTransform4f().look_at(origin=[0.0, 0.0, 0.0], target=[float(x) for x in ray], up=up)


PROFILE_DISTANCES_M = (0.005, 0.015, 0.03, 0.05, 0.075, 0.1, 0.15, 0.2)


def bias_profile(angle_deg: float, footprint_m2: float, config: Config, samples: int, columns: int = 96
                 ) -> list[tuple[float, float, float, float, float]]:
    """The 31.25 MHz multipath bias [m] across a corner of ``angle_deg`` at 2 m (its middle row), at each of
    PROFILE_DISTANCES_M from the edge: the project's renderer single-bounce and with three bounces, Mitsuba with
    one bounce (four path segments) and with nine. Rows (distance [m], the four biases [m])."""
    import dataclasses

    from mpi_lidar.physics.coupling import DEFAULT_COUPLING_GAIN
    from mpi_lidar.simulation.scenes import corner, light_transport

    scene = corner(angle_deg, 2.0, 0.8, 3, columns)
    radius = float(np.sqrt(footprint_m2 / (DEFAULT_COUPLING_GAIN * np.pi)))
    biases = []
    for bounces in (None, 3):
        rendered = scene if bounces is None else dataclasses.replace(scene, notes={**scene.notes, "bounces": 3.0})
        truth: dict[str, NDArray] = {}
        light_transport(rendered, config, radius, 0.01, DEFAULT_COUPLING_GAIN, truth)
        biases.append(truth["bias_m"][:, -1])
    for depth in (4, DEFAULT_MAX_DEPTH):
        biases.append(true_bias_m(path_trace(scene, config, footprint_m2, samples=samples, max_depth=depth),
                                  config).ravel())
    ranges, _ = first_hits(scene)
    across = np.abs(ranges * grid_rays(scene.azimuth_rad, scene.elevation_rad).reshape(-1, 3)[:, 0])
    middle = np.arange(ranges.size) // columns == 1
    rows = []
    for distance in PROFILE_DISTANCES_M:
        nearest = np.flatnonzero(middle)[np.argsort(np.abs(across[middle] - distance))[:2]]  # one per board
        rows.append((distance, *(float(np.mean(bias[nearest])) for bias in biases)))
    return rows


def main() -> None:
    import argparse
    import platform
    from datetime import date

    parser = argparse.ArgumentParser(description="The multipath bias across a corner: the project's renderer "
                                                 "against Mitsuba's path tracer.")
    parser.add_argument("--angle", type=float, default=60.0, help="The corner's angle [deg].")
    parser.add_argument("--footprint", type=float, default=0.073, help="The receiver footprint [m^2].")
    parser.add_argument("--samples", type=int, default=32768, help="Paths per pixel.")
    parser.add_argument("--columns", type=int, default=96,
                        help="Pixels across the view (3 rows): each is rendered, so fewer are quicker and coarser.")
    args = parser.parse_args()
    config = Config()
    print(f"corner {args.angle:g} deg at 2 m, albedo 0.8, footprint {args.footprint:g} m^2 (the beam's radius "
          f"{np.sqrt(args.footprint / np.pi):.3f} m at the pixel's range), {args.samples} paths per pixel; the "
          "31.25 MHz bias [mm] of the middle row, mean of the two boards\n")
    print("| across the view from the edge [m] | project, single bounce | project, 3 bounces | path traced, 1 bounce "
          "| path traced, 9 bounces |\n|---|---|---|---|---|")
    for distance, *biases in bias_profile(args.angle, args.footprint, config, args.samples, args.columns):
        print(f"| {distance:g} | " + " | ".join(f"{1e3 * b:.2f}" for b in biases) + " |")
    print(f"\n{platform.system()}, {platform.machine()}, Python {platform.python_version()}, {date.today()}")


if __name__ == "__main__":
    main()
