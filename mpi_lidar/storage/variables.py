"""Every array of the project's stores, declared once: its dimensions, dtype, units and meaning.

One :class:`Variable` per array and store (after sgkit's ``variables.py`` and its ``ArrayLikeSpec``). The
declarations drive what the stores write and check:

- the scan store (``*.scan.zarr``, :mod:`mpi_lidar.scans.store`): dimension names and the ``units`` and
  ``long_name`` attributes of every array, and the checks of a scan's shapes and dtypes
  (:func:`mpi_lidar.scans.scan.validate`);
- the corrected store (``corrected.zarr``): the same attributes, through
  :func:`mpi_lidar.scans.store.write_described_arrays`;
- the dataset store (``*.zarr`` of ``mpi-lidar simulate``): its arrays' dimensions, dtypes and attributes;
- the reference page ``docs/reference/stores.md`` (:func:`reference_markdown`), with the root attributes of the
  scan store (:data:`ATTRIBUTES`).

``kind`` is what a reader accepts (a numpy dtype kind: ``f`` floating point, ``b`` boolean, ``i`` signed and
``u`` unsigned integer), ``dtype`` what the project writes.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

import numpy as np
from numpy.typing import DTypeLike


class Store(StrEnum):
    """The stores the project writes."""

    SCAN = "scan"
    CORRECTED = "corrected"
    DATASET = "dataset"


# Dimensions of the same size in every store: the four taps of a measurement, a ray's three coordinates.
FIXED_SIZES = {"tap": 4, "xyz": 3}
# How a dtype kind reads in an error line and on the reference page.
KIND_NAMES = {"f": "floating point", "b": "boolean", "i": "integer", "u": "unsigned integer"}


@dataclass(frozen=True)
class Variable:
    """One array of one store.

    Attributes
    ----------
    name : The array's name in the store.
    store : The store that holds it.
    dims : Dimension names (written as the array's ``dimension_names``).
    kind : The dtype kind a reader accepts (see :data:`KIND_NAMES`).
    dtype : The dtype the project writes (``"as given"`` where it keeps the importer's floating dtype).
    units : UDUNITS units (written as ``units``; ``1`` for none).
    long_name : What it is, in a few words (written as ``long_name``).
    required : Whether every store of its kind holds it.
    coordinate : Whether it labels a dimension for xarray (no reader takes data from it).
    note : More on its meaning, for the reference page.
    """

    name: str
    store: Store
    dims: tuple[str, ...]
    kind: str
    dtype: str
    units: str
    long_name: str
    required: bool = False
    coordinate: bool = False
    note: str = ""

    def accepts(self, dtype: DTypeLike) -> bool:
        """Whether a reader takes an array of ``dtype`` for this variable."""
        return np.dtype(dtype).kind == self.kind

    def dtype_problem(self, dtype: DTypeLike) -> str | None:
        """The one-line problem of an array of ``dtype`` for this variable, or None if it is accepted."""
        if self.accepts(dtype):
            return None
        return f"{self.name} must be {KIND_NAMES[self.kind]}, got {np.dtype(dtype)}"

    def shape(self, sizes: Mapping[str, int]) -> tuple[int, ...]:
        """The shape the variable has in a store whose dimensions have ``sizes``."""
        return tuple(sizes[dim] for dim in self.dims)


_SCAN_NOTE = "Stores with taps only are read by demodulating them (depth and amplitude are then computed)."

VARIABLES: tuple[Variable, ...] = (
    # --- the scan store ---
    Variable("depth", Store.SCAN, ("frequency", "y", "x"), "f", "float32", "m", "measured range along the ray",
             required=True, note="NaN where nothing was measured. " + _SCAN_NOTE),
    Variable("amplitude", Store.SCAN, ("frequency", "y", "x"), "f", "float32", "V^2", "measured amplitude",
             required=True, note="Not negative. " + _SCAN_NOTE),
    Variable("azimuth_rad", Store.SCAN, ("x",), "f", "as given", "rad", "azimuth of the pixel column",
             note="With elevation_rad, the scan grid; a coordinate of x."),
    Variable("elevation_rad", Store.SCAN, ("y",), "f", "as given", "rad", "elevation of the pixel row",
             note="With azimuth_rad, the scan grid; a coordinate of y."),
    Variable("ray_directions", Store.SCAN, ("y", "x", "xyz"), "f", "as given", "1",
             "unit ray direction (x left, y up, z forward)", note="Instead of a scan grid."),
    Variable("reference_depth", Store.SCAN, ("y", "x"), "f", "as given", "m", "reference range along the ray",
             note="For evaluation only."),
    Variable("reference_mask", Store.SCAN, ("y", "x"), "b", "bool", "1",
             "reference region mask (1 where the reference holds)", note="For evaluation only."),
    Variable("taps", Store.SCAN, ("frequency", "tap", "y", "x"), "f", "float32", "V^2", "demodulation taps",
             note="The raw four-tap measurements the maps are demodulated from."),
    Variable("frequency_hz", Store.SCAN, ("frequency",), "f", "float64", "Hz", "modulation frequency",
             coordinate=True, note="Equal to the root attribute frequencies_hz, which readers use."),
    Variable("y", Store.SCAN, ("y",), "i", "int64", "1", "pixel row", coordinate=True,
             note="Written where the scan has no elevation_rad."),
    Variable("x", Store.SCAN, ("x",), "i", "int64", "1", "pixel column", coordinate=True,
             note="Written where the scan has no azimuth_rad."),
    # --- the corrected store ---
    Variable("corrected_depth", Store.CORRECTED, ("y", "x"), "f", "float32", "m", "corrected range along the ray",
             required=True, note="NaN where the pixel is invalid."),
    Variable("flags", Store.CORRECTED, ("y", "x"), "u", "uint8", "1", "what was done to the pixel",
             required=True, note="CF flag_values and flag_meanings name the codes (corrected, left as measured...)."),
    Variable("measured_depth", Store.CORRECTED, ("y", "x"), "f", "float32", "m",
             "measured range along the ray at the highest frequency",
             note="Unwrapped into one range where the scan's depths were wrapped; as measured where that range "
                  "is ambiguous (flag ambiguous)."),
    Variable("unwrap_confidence", Store.CORRECTED, ("y", "x"), "f", "float32", "1",
             "posterior probability of the chosen wrap counts",
             note="Written for scans whose depths came wrapped; 0 where a measurement is not finite."),
    Variable("estimate", Store.CORRECTED, ("y", "x"), "u", "uint8", "1", "which estimate the corrected depth is",
             note="CF flag_values and flag_meanings name the codes: none, measured, fused, corrected."),
    Variable("depth_uncertainty", Store.CORRECTED, ("y", "x"), "f", "float32", "m",
             "1-sigma uncertainty of the corrected depth",
             note="From the noise model and the multipath the scene geometry expects (measured and fused depths; "
                  "docs/explanation/footprint.md); for corrected depths from the model's own "
                  "error, fitted on its validation rows (card.json: uncertainty_model), and the footprint "
                  "estimate's uncertainty; for pixels resolved into two returns (flag two_returns) the two-return "
                  "fit's Cramer-Rao bound of the stronger return; NaN where the depth or the range is not known."),
    Variable("multipath_bias_m", Store.CORRECTED, ("y", "x"), "f", "float32", "m",
             "expected multipath bias (geometry gate)", note="Written by the geometry gate only."),
    Variable("second_return_depth", Store.CORRECTED, ("y", "x"), "f", "float32", "m",
             "range of the weaker of two returns (flag two_returns)",
             note="Written where some pixel was resolved into two returns; NaN elsewhere. corrected_depth holds "
                  "the stronger return's range."),
    Variable("second_return_share", Store.CORRECTED, ("y", "x"), "f", "float32", "1",
             "share of the light of the weaker of two returns (flag two_returns)",
             note="Its amplitude over the two returns' amplitudes; written with second_return_depth."),
    Variable("second_return_uncertainty", Store.CORRECTED, ("y", "x"), "f", "float32", "m",
             "1-sigma uncertainty of the weaker of two returns' range (flag two_returns)",
             note="The two-return fit's Cramer-Rao bound of second_return_depth; written with it. "
                  "depth_uncertainty holds the stronger return's from the same fit."),
    Variable("azimuth_rad", Store.CORRECTED, ("x",), "f", "as given", "rad", "azimuth of the pixel column",
             coordinate=True, note="The scan's, or worked out from its ray_directions where they form a regular "
             "grid. Where the grid is regular (each angle strictly monotonic), the maps' dimensions are "
             "(elevation_rad, azimuth_rad) instead of (y, x), with the angles as their dimension coordinates."),
    Variable("elevation_rad", Store.CORRECTED, ("y",), "f", "as given", "rad", "elevation of the pixel row",
             coordinate=True, note="As azimuth_rad: the scan's, or worked out from a regular grid of rays."),
    Variable("y", Store.CORRECTED, ("y",), "i", "int64", "1", "pixel row", coordinate=True,
             note="Written where the scan grid is not regular (no angles, or angles not monotonic)."),
    Variable("x", Store.CORRECTED, ("x",), "i", "int64", "1", "pixel column", coordinate=True,
             note="Written where the scan grid is not regular (no angles, or angles not monotonic)."),
    # --- the dataset store ---
    Variable("features", Store.DATASET, ("sample", "feature"), "f", "float32",
             "m (depth columns), V^2 (amplitude columns)", "measured depth then amplitude per modulation frequency",
             required=True, note="Its columns are named in the attribute columns."),
    Variable("target", Store.DATASET, ("sample",), "f", "float64", "m", "true distance d_AS to the surface",
             required=True),
    Variable("theta", Store.DATASET, ("sample", "parameter"), "f", "float64", "m (d_as_m, d_ab_m), 1 (reflectances)",
             "scene parameters", required=True, note="Its columns are named in the attribute columns."),
    Variable("split", Store.DATASET, ("sample",), "u", "uint8", "1", "train (0) or test (1) row", required=True),
    Variable("chunk_done", Store.DATASET, ("chunk",), "u", "uint8", "1", "chunk completion mark", required=True,
             note="1 once the chunk's rows and fingerprints are written."),
    Variable("chunk_sha256", Store.DATASET, ("chunk", "array", "byte"), "u", "uint8", "1",
             "SHA-256 of each data array's rows of the chunk", required=True,
             note="Written with the chunk's completion mark; a dataset without it is damaged."),
)


@dataclass(frozen=True)
class Attribute:
    """One root attribute of one store (JSON in the store's metadata).

    Attributes
    ----------
    name : The attribute's name.
    store : The store that holds it.
    units : Its units (``1`` for none).
    meaning : What it is, and what a store without it reads as.
    required : Whether every store of its kind holds it.
    """

    name: str
    store: Store
    units: str
    meaning: str
    required: bool = False


ATTRIBUTES: tuple[Attribute, ...] = (
    Attribute("schema", Store.SCAN, "1", "`mpi-lidar/scan@1`", required=True),
    Attribute("frequencies_hz", Store.SCAN, "Hz", "the modulation frequencies, in the order of the frequency axis",
              required=True),
    Attribute("name", Store.SCAN, "1", "the scan's name (the store's name without `.scan.zarr` where absent)"),
    Attribute("scene", Store.SCAN, "1", "free metadata (JSON object) of how the scan was made"),
    Attribute("depth_wrapped", Store.SCAN, "1",
              "whether each frequency's depth lies in [0, c / 2f), as its phase measures it (true where absent)"),
    Attribute("speed_of_light_m_per_s", Store.SCAN, "m/s",
              "the speed of light c the depths were converted from phases with: each frequency's wrap period is "
              "c / 2f. 3.0e8 (Table I) where absent, as in stores written before it; within 2.9e8-3.1e8"),
    Attribute("chunk_sha256", Store.SCAN, "1", "SHA-256 of every chunk of every array", required=True),
)


def variables(store: Store) -> dict[str, Variable]:
    """The variables of one store by name, in declaration order."""
    return {v.name: v for v in VARIABLES if v.store == store}


def attributes(store: Store) -> dict[str, tuple[str, str]]:
    """``(units, long_name)`` of every variable of a store, as its writer describes the arrays."""
    return {v.name: (v.units, v.long_name) for v in VARIABLES if v.store == store}


SCAN = variables(Store.SCAN)
CORRECTED = variables(Store.CORRECTED)
DATASET = variables(Store.DATASET)

_TITLES = {
    Store.SCAN: "Scan store (`*.scan.zarr`, schema `mpi-lidar/scan@1`)",
    Store.CORRECTED: "Corrected store (`corrected.zarr`, one per corrected scan)",
    Store.DATASET: "Dataset store (`mpi-lidar simulate --out`, schema `mpi-lidar/dataset@1`)",
}
REGENERATE = ".venv/bin/python -c 'from mpi_lidar.storage import variables as v; v.write_reference()'"
REFERENCE_PAGE = "docs/reference/stores.md"


def reference_markdown() -> str:
    """The reference page of the stores' arrays (``docs/reference/stores.md``), from :data:`VARIABLES`."""
    lines = ["# Store arrays", "",
             f"Generated from `mpi_lidar/storage/variables.py`; regenerate with `{REGENERATE}`.", "",
             "Every store is Zarr v3 with consolidated metadata; every array carries `units` and `long_name`",
             "and its dimension names, so `xarray.open_zarr` opens it. Kind is what a reader accepts:",
             ", ".join(f"`{kind}` {name}" for kind, name in KIND_NAMES.items()) + "."]
    for store in Store:
        lines += ["", f"## {_TITLES[store]}", "",
                  "| array | dimensions | kind | dtype | units | required | meaning |",
                  "|---|---|---|---|---|---|---|"]
        for v in variables(store).values():
            role = "coordinate" if v.coordinate else "yes" if v.required else "no"
            meaning = v.long_name + (f". {v.note}" if v.note else "")
            lines.append(f"| `{v.name}` | ({', '.join(v.dims)}) | `{v.kind}` | {v.dtype} | {v.units} | {role} "
                         f"| {meaning} |")
        declared = [a for a in ATTRIBUTES if a.store == store]
        if declared:
            lines += ["", "Root attributes:", "", "| attribute | units | required | meaning |", "|---|---|---|---|"]
            lines += [f"| `{a.name}` | {a.units} | {'yes' if a.required else 'no'} | {a.meaning} |" for a in declared]
    return "\n".join(lines) + "\n"


def write_reference(root: str = ".") -> None:
    """Write :func:`reference_markdown` to ``docs/reference/stores.md`` under ``root``."""
    page = Path(root) / REFERENCE_PAGE
    page.parent.mkdir(parents=True, exist_ok=True)
    page.write_text(reference_markdown())
