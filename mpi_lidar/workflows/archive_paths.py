"""Where a batch's scans come from and where their outputs go.

The inputs are scan stores named directly, found in a directory, or matched by a glob (:func:`expand_archive`).
Per scan the outputs (``corrected.zarr``, report files, point clouds) go into a directory named after the
scan store's path relative to the common root of the batch's inputs (the deepest directory holding all their
parent directories), with the ``.scan.zarr`` (or ``.zarr``) suffix removed: a directory of scans keeps their
names (``scenes/cornered_board.scan.zarr`` -> ``<out>/cornered_board/``), an archive with one folder per day
gets nested directories (``day1/frame.scan.zarr`` -> ``<out>/day1/frame/``). Every component must be a safe
name (letters, digits, ``. _ -``, starting with a letter or digit), or that scan fails. ``<out>/summary/`` is
the batch summary's: a scan (or folder) whose first component would be ``summary`` goes to ``summary.scan``
instead (``summary.scan.zarr`` -> ``<out>/summary.scan/``), so neither overwrites the other. Two inputs
mapping to one directory, or one inside another's, are refused before anything is written (the scan's own
``name`` attribute no longer decides where its outputs go, but it must still be a safe name: it names the
scan in every report).
"""

from __future__ import annotations

import glob
import os
import re
from pathlib import Path, PurePosixPath

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.locations import Location, location
from mpi_lidar.scans.store import SCAN_SUFFIX
from mpi_lidar.storage.objects import filesystem, store_error

SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")  # fullmatch: "$" would let a final newline pass
SUMMARY_NAME = "summary"  # <out>/summary/: the batch summary (mpi_lidar.reporting.batch_report)
RESERVED_SUFFIX = ".scan"  # a scan whose output would be <out>/summary/ goes to <out>/summary.scan/ instead


def safe_scan_name(name: str, what: str = "scan name", fix: str = "rename the scan") -> str:
    """``name`` as a directory name; anything that could escape the output directory is refused."""
    if not isinstance(name, str) or not SAFE_NAME.fullmatch(name) or ".." in name:
        raise MpiLidarError(f"{what} {name!r} is not a safe directory name (letters, digits, . _ -); {fix}")
    return name


def _store_stem(name: str) -> str:
    for suffix in (SCAN_SUFFIX, ".zarr"):
        if name.endswith(suffix):
            return name.removesuffix(suffix)
    return name


def scan_output_paths(sources: list[str]) -> dict[str, str]:
    """Each source's output directory, relative to the output directory (POSIX, ``/``-separated).

    The path of each store relative to the common root of all the sources' parent directories, suffix
    removed, a first component ``summary`` renamed ``summary.scan`` (see the module docstring). The
    components are not checked here (an unsafe one fails its scan alone, in
    :func:`~mpi_lidar.workflows.correct_archive.process_scan`); two sources mapping to one directory, or one
    into another's (compared without case, as a case-insensitive file system would), are refused with one
    error naming both, before anything is written.
    """
    if not sources:
        return {}
    places = {source: location(source) for source in sources}
    if len({place.scheme for place in places.values()}) > 1:
        raise MpiLidarError("the scans of one batch must all be local or all in one kind of store; correct them in "
                            "separate batches")
    absolute = {source: PurePosixPath("/" + place.path) if not place.is_local
                else Path(os.path.abspath(place.path)) for source, place in places.items()}
    root = PurePosixPath(os.path.commonpath([str(path.parent) for path in absolute.values()]))
    outputs: dict[str, str] = {}
    for source, path in absolute.items():
        parts = list(path.relative_to(root).parts)
        parts[-1] = _store_stem(parts[-1])
        if parts[0].casefold() == SUMMARY_NAME:
            parts[0] += RESERVED_SUFFIX
        outputs[source] = "/".join(parts)
    _refuse_collisions(outputs)
    return outputs


def _refuse_collisions(outputs: dict[str, str]) -> None:
    owner: dict[str, str] = {}
    for source, output in sorted(outputs.items()):
        key = output.casefold()
        if key in owner:
            raise MpiLidarError(f"scans {owner[key]} and {source} would both write {output}/; "
                                "correct them in separate batches or rename one")
        owner[key] = source
    for source, output in sorted(outputs.items()):
        for parent in PurePosixPath(output.casefold()).parents:
            if str(parent) in owner:
                raise MpiLidarError(f"scan {source} would write {output}/ inside the outputs of "
                                    f"{owner[str(parent)]} ({outputs[owner[str(parent)]]}/); correct them in "
                                    "separate batches or move one")


def safe_output(out_dir: Path | Location, output: str) -> Path | Location:
    """``out_dir`` joined with ``output`` after every component passed the safe-name rule."""
    for part in output.split("/"):
        safe_scan_name(part, "output directory component",
                       f"rename that folder or scan store (output {output!r})")
    return out_dir.joinpath(*output.split("/"))


def expand_archive(inputs: list[str]) -> list[str]:
    """Scan stores named directly, found in a directory, or matched by a glob; sorted and unique.

    Refused with one line, before anything is read or written: a path that does not exist, a glob that matches
    no scan store, a directory that holds none, and a file of another tool (pointed to ``import-scan``).
    """
    found: list[str] = []
    for item in inputs:
        place = location(item)
        if not place.is_local:
            found += _expand_in_store(item, place)
            continue
        path = place.local_path()
        if glob.has_magic(item):
            matches = [m for m in sorted(glob.glob(item)) if _is_scan_store(Path(m))]
            if not matches:
                raise MpiLidarError(f"{item} matches no scan store; give *{SCAN_SUFFIX} stores, a directory or a "
                                    f"glob of them{_import_hint(sorted(glob.glob(item)))}")
            found += matches
        elif _is_scan_store(path):
            found.append(str(path))
        elif not path.exists():
            raise MpiLidarError(f"{item} does not exist; give *{SCAN_SUFFIX} stores, a directory or a glob of them")
        elif path.is_dir():
            stores = sorted(str(p) for p in path.glob(f"*{SCAN_SUFFIX}") if _is_scan_store(p))
            if not stores:
                raise MpiLidarError(f"directory {item} holds no *{SCAN_SUFFIX} store"
                                    f"{_import_hint([str(p) for p in path.iterdir()])}")
            found += stores
        else:
            raise MpiLidarError(f"{item} is not a scan store (*{SCAN_SUFFIX}){_import_hint([item])}")
    return sorted(dict.fromkeys(found))


def _expand_in_store(item: str, place: Location) -> list[str]:
    """:func:`expand_archive` of one object-store URL: a scan store, a prefix holding some (one listing of its
    children, none of their chunks) or a glob of them; the URLs found."""
    fs = filesystem(place)
    try:
        if glob.has_magic(item):
            candidates = sorted(str(m) for m in fs.glob(place.path))
        elif fs.exists(f"{place.path}/zarr.json"):
            return [place.url]
        else:
            candidates = sorted(str(m) for m in fs.ls(place.path, detail=False) if str(m).endswith(SCAN_SUFFIX))
    except FileNotFoundError:
        candidates = []
    except Exception as exc:  # botocore raises many types
        raise store_error(place, exc, "list") from None
    found = [f"{place.scheme}://{m.removeprefix(place.scheme + '://').rstrip('/')}" for m in candidates
             if m.rstrip("/").endswith(SCAN_SUFFIX)]
    if not found:
        raise MpiLidarError(f"{place} holds no *{SCAN_SUFFIX} store; give *{SCAN_SUFFIX} stores, a prefix or a glob "
                            "of them")
    return found


def _is_scan_store(path: Path) -> bool:
    """A Zarr store (its ``zarr.json``), or anything named ``*.scan.zarr`` that exists: whether it is a readable
    scan is for :func:`~mpi_lidar.scans.store.read_scan`, and a damaged one fails alone."""
    return (path.is_dir() and (path / "zarr.json").exists()) or (path.name.endswith(SCAN_SUFFIX) and path.exists())


def _import_hint(paths: list[str]) -> str:
    """A pointer to ``import-scan`` where ``paths`` hold files it reads; nothing otherwise."""
    from mpi_lidar.scans.importers import IMPORT_SUFFIXES

    importable = [p for p in paths if Path(p).suffix.lower() in IMPORT_SUFFIXES]
    if not importable:
        return ""
    return f"; {Path(importable[0]).name} is another tool's file: convert it first with mpi-lidar import-scan"
