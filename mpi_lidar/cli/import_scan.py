"""mpi-lidar import-scan: scan stores from .npz archives, NetCDF/HDF5 files and Zarr groups."""

from __future__ import annotations

from pathlib import Path

import click

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.locations import Location, is_url, location


@click.command("import-scan")
@click.argument("sources", nargs=-1, required=True)
@click.option("--out", required=True,
              help="Scan store to write (X.scan.zarr) for one file, or a directory: OUT/<name>.scan.zarr per file; "
                   "a path or a URL (s3://, gs://, az://).")
@click.option("--frequencies", help="Comma-separated frequencies in Hz, if the files do not hold frequencies_hz.")
@click.option("--var", "variables", multiple=True, metavar="NAME=VARIABLE",
              help="Read the scan array NAME (depth, amplitude, taps, azimuth_rad, elevation_rad, azimuth_deg, "
                   "elevation_deg, reference_depth, frequencies_hz, ...) from the file's VARIABLE (array of an "
                   ".npz or a Zarr group); ignore=VAR1,VAR2 leaves variables out on purpose; repeatable. A variable "
                   "neither known nor mapped is refused; only regular files of at most 2 GiB are read, and all stores "
                   "are written or none.")
@click.option("--depths", type=click.Choice(["wrapped", "unwrapped"]), default="wrapped", show_default=True,
              help="wrapped: each frequency's depth lies in [0, c/2f), as its phase measures it (correction "
                   "unwraps them into one range, out to 24 m at 12.5-31.25 MHz); unwrapped: the scanner gives "
                   "one range per frequency already.")
@click.option("--speed-of-light", "speed_of_light", type=float, metavar="M_PER_S",
              help="The speed of light the scanner converted phase to range with, in m/s, where the files hold "
                   "neither speed_of_light_m_per_s nor wrap_period_m (each frequency's c/2f) [default: 299792458]. "
                   "A wrapped depth beyond its frequency's c/2f refuses the import.")
def import_scan(sources: tuple[str, ...], out: str, frequencies: str | None, variables: tuple[str, ...],
                depths: str, speed_of_light: float | None) -> None:
    """Import scans from .npz archives, NetCDF/HDF5 files (.nc, .h5, .hdf5) or Zarr groups (.zarr): files,
    directories or globs.

    \b
    Example:
      mpi-lidar import-scan 'day1/*.nc' --out scans/day1 --var depth=range_m --var amplitude=intensity

    Each file holds depth and amplitude (F, H, W), or taps (F, 4, H, W), plus optional geometry and reference,
    named as in a scan store or mapped with --var (e.g. --var depth=range_m --var amplitude=intensity).
    The file's attributes (instrument, serial, a scalar timestamp, ...) are kept in the scan's scene metadata.
    Every file is read and checked before anything is written: one bad file refuses the whole import with one
    error line (exit 2), and nothing is written. Files whose store is already in the --out directory are not
    imported again (named on stderr); the others are added.
    """
    from mpi_lidar.scans.importers import find_scan_files, import_files, new_stores, plan_import
    from mpi_lidar.scans.importers.base import check_frequencies_in_hz
    from mpi_lidar.scans.scan import check_speed_of_light

    freqs = None
    if frequencies:
        try:
            freqs = tuple(float(f) for f in frequencies.split(","))
        except ValueError:
            raise MpiLidarError(f"--frequencies must be comma-separated numbers in Hz, got {frequencies!r}") from None
        check_frequencies_in_hz(freqs, "--frequencies")  # before any file is read
    if speed_of_light is not None:
        check_speed_of_light(speed_of_light, "--speed-of-light")  # before any file is read
    mapping = variable_mapping(variables)
    if is_url(out):  # into a bucket: written locally, all or none, then each store published there
        _import_into_store(sources, location(out), freqs, mapping, depths == "wrapped", speed_of_light)
        return
    plan, existing = new_stores(plan_import(find_scan_files(sources), out))

    def echo(scan, target: Path) -> None:
        click.echo(f"scan {scan.name}: {scan.shape[0]} x {scan.shape[1]} pixels at {len(scan.frequencies_hz)} "
                   f"frequencies (c = {scan.speed_of_light_m_per_s:.9g} m/s) written to {target}")

    import_files(plan, freqs, mapping, on_scan=echo, depth_wrapped=depths == "wrapped",
                 speed_of_light_m_per_s=speed_of_light)
    if existing:
        names = ", ".join(f"{source.name} ({target.name})" for source, target in existing)
        click.echo(f"import-scan: not imported, their stores already exist in {out}: {names}; remove a store to "
                   "import its file again", err=True)


def _import_into_store(sources: tuple[str, ...], out: Location, freqs: tuple[float, ...] | None,
                       mapping: dict[str, str], depth_wrapped: bool, speed_of_light: float | None) -> None:
    """``import-scan`` into an object store (:func:`mpi_lidar.workflows.remote_outputs.import_into_store`)."""
    from mpi_lidar.scans.importers import find_scan_files, import_files
    from mpi_lidar.workflows.remote_outputs import import_into_store

    def run(plan: list[tuple[Path, Path]]) -> None:
        import_files(plan, freqs, mapping, depth_wrapped=depth_wrapped, speed_of_light_m_per_s=speed_of_light)

    imported, existing = import_into_store(find_scan_files(sources), out, run)
    for source, target in imported:
        click.echo(f"scan {source.name} written to {target}")
    if existing:
        names = ", ".join(f"{source.name} ({target.name})" for source, target in existing)
        click.echo(f"import-scan: not imported, their stores already exist in {out}: {names}; remove a store to "
                   "import its file again", err=True)


def variable_mapping(variables: tuple[str, ...]) -> dict[str, str]:
    """The ``--var NAME=VARIABLE`` options as a mapping of names to the files' variables."""
    mapping = {}
    for item in variables:
        name, sep, variable = item.partition("=")
        if not sep or not name.strip() or not variable.strip():
            raise MpiLidarError(f"--var must be NAME=VARIABLE (e.g. depth=range_m), got {item!r}")
        if name.strip() in mapping:
            raise MpiLidarError(f"--var maps {name.strip()!r} twice")
        mapping[name.strip()] = variable.strip()
    return mapping
