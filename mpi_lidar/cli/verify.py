"""mpi-lidar verify: every chunk of a store against the fingerprints written with it."""

from __future__ import annotations

import sys

import click

from mpi_lidar.errors import EXIT_FAILURE, MpiLidarError
from mpi_lidar.redact import redact


@click.command()
@click.argument("stores", nargs=-1, required=True)
def verify(stores: tuple[str, ...]) -> None:
    """Check datasets, scans and corrected outputs chunk by chunk against the fingerprints written with them.

    A store may be a path or an object-store URL (s3://bucket/out/scan: published outputs, every object
    checked). Prints one line per store; exits 1 if any store is damaged (a deleted, truncated or replaced
    chunk), naming the array and chunk.

    \b
    Example:
      mpi-lidar verify runs/quick/dataset.zarr runs/quick/scenes/*.scan.zarr runs/quick/corrected/*
    """
    from mpi_lidar.workflows.verify import verify_store

    damaged = 0
    for store in stores:
        try:
            result = verify_store(store)
        except MpiLidarError as exc:
            damaged += 1
            click.echo(f"error: {redact(str(exc))}", err=True)
            continue
        click.echo(f"ok {result.path}: {result.kind}, {result.chunks:,} chunks")
    if damaged:
        sys.exit(EXIT_FAILURE)
