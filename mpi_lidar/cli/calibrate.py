"""mpi-lidar calibrate: a sensor profile measured on the sensor's own scans."""

from __future__ import annotations

from pathlib import Path

import click


@click.command()
@click.argument("scans", nargs=-1, required=True)
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Sensor profile to write (.toml).")
@click.option("--no-reference", is_flag=True,
              help="Measure against each scan's own surfaces even where it has a reference depth.")
def calibrate(scans: tuple[str, ...], out: Path, no_reference: bool) -> None:
    """Measure your sensor's receiver footprint on its scans and write a sensor profile for correct --sensor.

    \b
    Example:
      mpi-lidar calibrate 'archive/corners/*.scan.zarr' --out sensor.toml

    Each scan's footprint comes from the depth and amplitude near its facing surfaces (against its reference
    depth where it has one); the estimates are pooled by their uncertainty. Scans of corners work best. Each
    scan's line says what it measured (footprint, amplitude unit, noise scale, frequency offsets, speed of
    light). Nothing is written (exit 2) when the pooled estimate is not significant, or when the scans disagree:
    other frequencies or speeds of light, or amplitude units more than twofold apart.
    """
    from mpi_lidar.workflows.calibrate import calibrate_scans, describe_scan

    profile, _ = calibrate_scans(list(scans), out, use_reference=not no_reference,
                                 on_scan=lambda r: click.echo(describe_scan(r)))
    sigma = profile.calibration["sigma_m2"] if profile.calibration else float("nan")
    click.echo(f"footprint {profile.footprint_area_m2:.4g} +- {sigma:.2g} m^2; amplitude unit "
               f"{profile.amplitude_scale:.4g} per V^2; noise scale "
               + ("not measured" if profile.noise_scale is None else f"{profile.noise_scale:.3g}")
               + _offsets_said(profile.frequency_offsets_m, profile.window_leakage_removed)
               + (f"; range {profile.range_m[0]:.2f}-{profile.range_m[1]:.2f} m" if profile.range_m else "")
               + (f"; c = {profile.speed_of_light_m_per_s:.9g} m/s" if profile.speed_of_light_m_per_s else "")
               + f"; sensor profile written to {out}")


def _offsets_said(offsets_m: tuple[float, ...] | None, window_leakage_removed: bool | None) -> str:
    """What calibrate says of the frequencies' offsets and the window's leakage."""
    if offsets_m is None:
        return "; frequency offsets not measured"
    from mpi_lidar.reporting.correction_notes import offsets_mm

    listed = offsets_mm(offsets_m)
    leakage = "removed first" if window_leakage_removed else "left in"
    return f"; frequency offsets {listed} mm (the integration window's leakage {leakage})"
