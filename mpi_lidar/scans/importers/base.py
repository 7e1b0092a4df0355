"""The interface of a scan importer, and what every importer shares: the names a file's arrays may map to,
and the building of a validated :class:`~mpi_lidar.scans.scan.Scan` from plain arrays."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.constants import TABLE_SPEED_OF_LIGHT_M_PER_S
from mpi_lidar.scans.scan import OPTIONAL_ARRAYS, Scan, ScanError, from_taps, scan_extras, validate

# The names a file's variables can be mapped to (``--var NAME=VARIABLE``).
SCAN_VARIABLES = ("depth", "amplitude", *OPTIONAL_ARRAYS, "frequencies_hz")


class ScanImporter(ABC):
    """Reads the files of one format into a scan.

    The contract every importer keeps:

    - **What it reads**: a file whose name ends in one of :attr:`suffixes` (lower case; the registry in
      :mod:`mpi_lidar.scans.importers` picks the importer by suffix). Its arrays are named as in the scan store
      (:data:`SCAN_VARIABLES`), or mapped by ``variables`` (scan name -> the file's own name, checked with
      :func:`check_variables`); other arrays are refused or ignored as the format documents. The frequencies
      come from ``frequencies_hz`` when given, else from the file.
    - **Before reading values** it checks every array's declared dtype (numbers and booleans only) and size
      against the memory budget (:func:`mpi_lidar.scans.store.check_memory_budget`), so a damaged or hostile
      file is refused without allocating what it claims; declared units are converted to the store's.
    - **What it returns**: a validated :class:`Scan` (float32 maps) built by :func:`import_arrays`, named after
      the file.
    - **What it raises**: :class:`ScanError` (one line naming the file and what to do) for anything wrong with
      the file: unreadable, foreign or damaged, arrays missing, of the wrong dtype, shape or units, over the
      budget. Never another exception type for a bad file.
    """

    suffixes: ClassVar[tuple[str, ...]]

    @abstractmethod
    def load(self, path: Path, frequencies_hz: tuple[float, ...] | None = None,
             variables: Mapping[str, str] | None = None) -> Scan:
        """The scan in the file at ``path`` (see the class's contract)."""


def import_arrays(
    name: str, frequencies_hz: tuple[float, ...], arrays: dict[str, NDArray], c: float = TABLE_SPEED_OF_LIGHT_M_PER_S,
    source: str | None = None,
) -> Scan:
    """A scan from plain arrays (e.g. an ``.npz`` from another tool): depth+amplitude or taps, plus extras.

    ``source`` (default ``name``) names where the arrays come from in the error messages, e.g. the file.
    """
    source = source or name
    check_frequencies_in_hz(frequencies_hz, source)
    known = {"depth", "amplitude", *OPTIONAL_ARRAYS}
    unknown = sorted(set(arrays) - known - {"frequencies_hz"})
    if unknown:
        raise ScanError(f"{source}: unknown arrays {unknown}; expected some of {sorted(known)}")
    optional = {k: np.asarray(v) for k, v in arrays.items() if k in OPTIONAL_ARRAYS and k != "taps"}
    if "reference_mask" in optional:
        optional["reference_mask"] = _boolean_mask(source, optional["reference_mask"])
    if "depth" in arrays and "amplitude" in arrays:
        scan = Scan(name=name, frequencies_hz=tuple(frequencies_hz), depth=np.asarray(arrays["depth"]),
                    amplitude=np.asarray(arrays["amplitude"]), taps=arrays.get("taps"), **scan_extras(optional))
    elif "taps" in arrays:
        try:
            scan = from_taps(name, tuple(frequencies_hz), np.asarray(arrays["taps"]), c, **scan_extras(optional))
        except ScanError as exc:
            raise ScanError(f"{source}: {str(exc).removeprefix(f'{name}: ')}") from None
    else:
        raise ScanError(f"{source}: needs arrays 'depth' and 'amplitude' (F, H, W), or 'taps' (F, 4, H, W)")
    return validate(scan, source)


# The lowest modulation frequency taken as one [Hz]: an AMCW scanner modulates at MHz; a value below this is
# a frequency written in MHz or kHz (12.5 for 12.5 MHz), which would unwrap and correct nothing right.
MIN_MODULATION_HZ = 1e4


def check_frequencies_in_hz(frequencies_hz: Sequence[float], source: str) -> None:
    """Refuse frequencies that are not positive numbers of Hz, or that look like MHz, with one line."""
    for f in frequencies_hz:
        if not np.isfinite(f) or f <= 0:
            raise ScanError(f"{source}: frequency {f!r} is not a positive number of Hz")
        if f < MIN_MODULATION_HZ:
            raise ScanError(f"{source}: frequency {f:g} Hz is below {MIN_MODULATION_HZ:g} Hz; frequencies are in Hz "
                            f"({f:g} MHz is {f * 1e6:g})")


def _boolean_mask(name: str, mask: NDArray) -> NDArray[np.bool_]:
    """A 0/1 mask of any numeric type as booleans; anything else is refused rather than guessed."""
    if mask.dtype != np.bool_ and not (np.issubdtype(mask.dtype, np.number) and np.isin(mask, (0, 1)).all()):
        raise ScanError(f"{name}: reference_mask must be boolean or 0/1, got {mask.dtype} with other values")
    return mask.astype(bool)


def stored_frequencies(path: Path, stored: NDArray) -> NDArray:
    """The frequencies [Hz] a file holds, checked: a non-empty 1-D array of numbers."""
    if stored.ndim != 1 or stored.size == 0 or not np.issubdtype(stored.dtype, np.number):
        raise ScanError(f"{path}: frequencies_hz must be a 1-D array of numbers in Hz, got "
                        f"{stored.dtype}{stored.shape}; pass --frequencies instead")
    return stored


def check_variables(variables: Mapping[str, str] | None) -> dict[str, str]:
    """A mapping of scan array names to a file's variable names, checked: known names, one variable each."""
    variables = dict(variables or {})
    unknown = sorted(set(variables) - set(SCAN_VARIABLES))
    if unknown:
        raise ScanError(f"--var names {unknown}, which are not scan arrays; map some of {list(SCAN_VARIABLES)}")
    shared = sorted({v for v in variables.values() if list(variables.values()).count(v) > 1})
    if shared:
        raise ScanError(f"--var maps several scan arrays to the variable(s) {shared}; map each variable once")
    return variables

