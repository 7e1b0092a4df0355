"""The interface of a scan importer, and what every importer shares: which of a file's variables become
which scan array (:func:`select_variables`: mapped, picked up by name, or refused), the checks of the file
itself (:func:`check_regular_file`) and of its angles and frequencies, and the building of a validated
:class:`~mpi_lidar.scans.scan.Scan` from plain arrays (:func:`import_arrays`)."""

from __future__ import annotations

import os
import stat
from abc import ABC, abstractmethod
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.constants import SPEED_OF_LIGHT_M_PER_S
from mpi_lidar.scans.scan import (
    OPTIONAL_ARRAYS,
    Scan,
    ScanError,
    check_speed_of_light,
    from_taps,
    scan_extras,
    validate,
)
from mpi_lidar.scans.store import MAX_SCAN_BYTES

# What sets a scan's wrap periods in a file: its speed of light [m/s] (a scalar), or the wrap period c / 2f of
# each frequency [m] (F,).
WRAP_VARIABLES = ("speed_of_light_m_per_s", "wrap_period_m")
# The names a file's variables can be mapped to (``--var NAME=VARIABLE``): the scan store's own.
SCAN_VARIABLES = ("depth", "amplitude", *OPTIONAL_ARRAYS, "frequencies_hz", *WRAP_VARIABLES)
# How far the speeds of light of a file's wrap periods (c = 2 f L per frequency), or of a file and an option,
# may differ and still be one speed of light [1]: float rounding of the periods, not another c.
SPEED_OF_LIGHT_AGREEMENT = 1e-6
# Other names of the same arrays, picked up in a file and accepted by ``--var``: the plain angle names (in
# radians, or in the unit a NetCDF ``units`` attribute declares) and the store's frequency coordinate.
ALIASES: dict[str, str] = {"azimuth": "azimuth_rad", "elevation": "elevation_rad", "frequency_hz": "frequencies_hz"}
# Angle names whose values are degrees, converted to radians on import.
DEGREE_NAMES: dict[str, str] = {"azimuth_deg": "azimuth_rad", "elevation_deg": "elevation_rad"}
# ``--var ignore=VARIABLE[,VARIABLE...]``: variables of the file deliberately left out of the scan.
IGNORE = "ignore"
VARIABLE_NAMES = (*SCAN_VARIABLES, *ALIASES, *DEGREE_NAMES)
# The largest file an importer opens [bytes]: twice the arrays a scan may hold in memory
# (:data:`~mpi_lidar.scans.store.MAX_SCAN_BYTES`, 1 GiB), room for float64 copies and the format's overhead.
MAX_FILE_BYTES = 2 * MAX_SCAN_BYTES


class ScanImporter(ABC):
    """Reads the files of one format into a scan.

    The contract every importer keeps:

    - **What it reads**: a file (a directory for Zarr) whose name ends in one of :attr:`suffixes` (lower case;
      the registry in :mod:`mpi_lidar.scans.importers` picks the importer by suffix), once
      :meth:`check_source` accepts the path. Its arrays are named as in the scan store
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

    def check_source(self, path: Path) -> None:
        """Refuse, before anything is opened, a path this importer cannot read safely (by default anything
        but a regular file of at most :data:`MAX_FILE_BYTES`: :func:`check_regular_file`)."""
        check_regular_file(path)

    @abstractmethod
    def load(self, path: Path, frequencies_hz: tuple[float, ...] | None = None,
             variables: Mapping[str, str] | None = None, speed_of_light_m_per_s: float | None = None) -> Scan:
        """The scan in the file at ``path`` (see the class's contract)."""


def import_arrays(
    name: str, frequencies_hz: tuple[float, ...], arrays: dict[str, NDArray], c: float = SPEED_OF_LIGHT_M_PER_S,
    source: str | None = None,
) -> Scan:
    """A scan from plain arrays (e.g. an ``.npz`` from another tool): depth+amplitude or taps, plus extras.

    ``c`` is the speed of light the scanner converted phase to range with [m/s] (the scan's, and what taps are
    demodulated with); ``source`` (default ``name``) names where the arrays come from in the error messages, e.g.
    the file.
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
                    amplitude=np.asarray(arrays["amplitude"]), taps=arrays.get("taps"),
                    speed_of_light_m_per_s=check_speed_of_light(c, source), **scan_extras(optional))
    elif "taps" in arrays:
        try:
            scan = from_taps(name, tuple(frequencies_hz), np.asarray(arrays["taps"]), c, **scan_extras(optional))
        except ScanError as exc:
            raise ScanError(f"{source}: {str(exc).removeprefix(f'{name}: ')}") from None
    else:
        raise ScanError(f"{source}: needs arrays 'depth' and 'amplitude' (F, H, W), or 'taps' (F, 4, H, W)")
    return validate(scan, source)  # shapes, dtypes and the geometry's values (angles in radians, unit rays)


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


def speed_of_light_of(source: str, frequencies_hz: Sequence[float], stored: NDArray | None = None,
                      wrap_periods_m: NDArray | None = None, given: float | None = None) -> float:
    """The speed of light a file's scan was converted with [m/s]: the file's ``speed_of_light_m_per_s``
    (``stored``), or the one its per-frequency wrap periods c / 2f give (``wrap_periods_m``, c = 2 f L, the same
    for every frequency), or ``given`` (``--speed-of-light``), or else the physical 299,792,458 m/s. Values that
    disagree (beyond :data:`SPEED_OF_LIGHT_AGREEMENT`) are refused with one line."""
    found: dict[str, float] = {}
    if stored is not None:
        values = np.asarray(stored)
        if values.size != 1 or not np.issubdtype(values.dtype, np.number):
            raise ScanError(f"{source}: speed_of_light_m_per_s must be one number in m/s, got {values.dtype}"
                            f"{values.shape}")
        found["its speed_of_light_m_per_s"] = check_speed_of_light(float(values.reshape(-1)[0]), source)
    if wrap_periods_m is not None:
        found["its wrap_period_m"] = _speed_of_periods(source, frequencies_hz, np.asarray(wrap_periods_m))
    if given is not None:
        found["--speed-of-light"] = check_speed_of_light(given, "--speed-of-light")
    if not found:
        return SPEED_OF_LIGHT_M_PER_S
    (first, c), *others = found.items()
    for what, other in others:
        if abs(other - c) > SPEED_OF_LIGHT_AGREEMENT * c:
            raise ScanError(f"{source}: {first} gives c = {c:.9g} m/s but {what} {other:.9g} m/s; give one (leave "
                            "the file's out with --var ignore=VARIABLE)")
    return c


def _speed_of_periods(source: str, frequencies_hz: Sequence[float], periods: NDArray) -> float:
    """The speed of light 2 f L of per-frequency wrap periods L [m], the same at every frequency [m/s]."""
    if periods.shape != (len(frequencies_hz),) or not np.issubdtype(periods.dtype, np.number):
        raise ScanError(f"{source}: wrap_period_m must hold one period in m per frequency ({len(frequencies_hz)}), "
                        f"got {periods.dtype}{periods.shape}")
    speeds = 2 * np.asarray(frequencies_hz, dtype=np.float64) * periods.astype(np.float64)
    if not np.isfinite(speeds).all() or np.ptp(speeds) > SPEED_OF_LIGHT_AGREEMENT * abs(float(speeds.mean())):
        listed = ", ".join(f"{c:.9g}" for c in speeds)
        raise ScanError(f"{source}: wrap_period_m gives other speeds of light (2 f L) at its frequencies ({listed} "
                        "m/s); each frequency's period is c / 2f of one c: check the periods and frequencies")
    return check_speed_of_light(float(speeds.mean()), f"{source}: wrap_period_m")


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
    """A mapping of scan array names to a file's variable names, checked: known names (:data:`VARIABLE_NAMES`,
    or :data:`IGNORE` with a comma-separated list), one variable each, each scan array mapped once."""
    variables = dict(variables or {})
    unknown = sorted(set(variables) - {*VARIABLE_NAMES, IGNORE})
    if unknown:
        raise ScanError(f"--var names {unknown}, which are not scan arrays; map some of {list(VARIABLE_NAMES)}, "
                        f"or leave variables out with --var {IGNORE}=VARIABLE[,VARIABLE...]")
    named = [v for k, v in variables.items() if k != IGNORE] + _ignored(variables)
    shared = sorted({v for v in named if named.count(v) > 1})
    if shared:
        raise ScanError(f"--var maps several scan arrays to the variable(s) {shared}; map each variable once")
    canonical = [_canonical(k) for k in variables if k != IGNORE]
    twice = sorted({k for k in canonical if canonical.count(k) > 1})
    if twice:
        raise ScanError(f"--var maps {twice[0]} twice (under two of its names); map it once")
    return variables


@dataclass(frozen=True)
class Selected:
    """A file's variable chosen for a scan array."""

    variable: str  # its name in the file
    degrees: bool = False  # it holds degrees (a name of DEGREE_NAMES): converted to radians


def select_variables(source: str, held: Collection[str], variables: Mapping[str, str] | None = None,
                     metadata: Collection[str] = ()) -> dict[str, Selected]:
    """Which of a file's variables (``held``) become which scan array: scan name -> :class:`Selected`.

    Every variable is accounted for: mapped by ``variables`` (``--var``), picked up by its own name (a name of
    :data:`SCAN_VARIABLES`, :data:`ALIASES` or :data:`DEGREE_NAMES`), left out with ``--var ignore=...``, or one
    of ``metadata`` (what the format documents as not data, e.g. a NetCDF dimension coordinate). Any other
    variable is refused with one line naming it and the ``--var`` that maps or leaves it out, so nothing a file
    holds is dropped silently.
    """
    variables = check_variables(variables)
    ignored = set(_ignored(variables))
    mapped = {name: v for name, v in variables.items() if name != IGNORE}
    missing = sorted([f"{name}={v}" for name, v in mapped.items() if v not in held]
                     + [f"{IGNORE}={v}" for v in ignored if v not in held])
    if missing:
        raise ScanError(f"{source} has no variable for --var {', '.join(missing)}; it holds {sorted(held)}")
    chosen = {_canonical(name): Selected(v, name in DEGREE_NAMES) for name, v in mapped.items()}
    taken = set(mapped.values()) | ignored
    clash, unknown = [], []
    for variable in sorted(held):
        if variable in taken:
            continue
        if variable in VARIABLE_NAMES:
            name = _canonical(variable)
            if name not in chosen:
                chosen[name] = Selected(variable, variable in DEGREE_NAMES)
                continue
            if chosen[name].variable in mapped.values():
                clash.append(variable)
                continue
            raise ScanError(f"{source} holds both {chosen[name].variable!r} and {variable!r} for {name}; choose one "
                            f"with --var {IGNORE}={variable} (or --var {IGNORE}={chosen[name].variable})")
        if variable not in metadata:
            unknown.append(variable)
    if clash:
        raise ScanError(f"{source} holds {clash} itself and --var maps other arrays to them; remove one or the "
                        f"other, or leave it out with --var {IGNORE}={','.join(clash)}")
    needed = [] if "taps" in chosen else [name for name in ("depth", "amplitude") if name not in chosen]
    if unknown and needed:  # some of them hold the measurements: never suggest leaving those out
        raise ScanError(f"{source} holds no {' or '.join(needed)} under the scan store's names; map "
                        f"{'them' if len(needed) > 1 else 'it'} from its variables {unknown} with "
                        f"{' '.join(f'--var {name}=VARIABLE' for name in needed)} (or --var taps=VARIABLE)")
    if unknown:
        what = (f"variable {unknown[0]!r} is not a scan array" if len(unknown) == 1
                else f"variables {unknown} are not scan arrays")
        raise ScanError(f"{source}: {what} and would be dropped; map it with --var NAME="
                        f"{unknown[0]} (NAME: {', '.join(VARIABLE_NAMES)}) or leave it out with --var "
                        f"{IGNORE}={','.join(unknown)}")
    return chosen


def _canonical(name: str) -> str:
    return ALIASES.get(name) or DEGREE_NAMES.get(name) or name


def _ignored(variables: Mapping[str, str]) -> list[str]:
    return [v.strip() for v in variables.get(IGNORE, "").split(",") if v.strip()]


def check_regular_file(path: Path) -> None:
    """Refuse, before anything is opened, a path that is not a regular file (a directory, a FIFO, a device
    such as /dev/zero, or a symbolic link to one) or that is larger than :data:`MAX_FILE_BYTES`."""
    try:
        info = os.stat(path)  # follows links; never blocks on a FIFO
    except FileNotFoundError:
        raise ScanError(f"{path} does not exist") from None
    except OSError as exc:
        raise ScanError(f"cannot read {path}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(info.st_mode):
        kind = ("a directory" if stat.S_ISDIR(info.st_mode) else "a FIFO (named pipe)" if stat.S_ISFIFO(info.st_mode)
                else "a socket" if stat.S_ISSOCK(info.st_mode) else "a device")
        link = ", through a symbolic link," if path.is_symlink() else ""
        raise ScanError(f"{path} is{link} {kind}, not a regular file; import-scan reads regular files only: copy "
                        "the scan into a file")
    if info.st_size > MAX_FILE_BYTES:
        raise ScanError(f"{path} is {info.st_size / 2**30:.1f} GiB, more than the {MAX_FILE_BYTES / 2**30:g} GiB "
                        "an imported file may be; split the scan into smaller files")

