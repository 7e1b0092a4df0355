"""Open and plot a store in xarray with every warning an error: what a user's notebook would see."""

from __future__ import annotations

import warnings

import xarray as xr
from matplotlib.figure import Figure


def open_strictly(path) -> xr.Dataset:
    """The store in xarray, every warning an error (unconsolidated metadata, decoding, ...), values loaded."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return xr.open_zarr(path).load()


def plot_strictly(array: xr.DataArray) -> None:
    """xarray's default plot of ``array`` on a figure of its own (pyplot's state untouched), warnings as errors."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        array.plot(ax=Figure().add_subplot())
