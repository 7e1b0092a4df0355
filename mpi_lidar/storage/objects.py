"""Object stores (S3 and its compatibles, Google Cloud Storage, Azure Blob Storage): opening, listing, reading,
and publishing a directory of outputs (or a store, or a model) without a rename.

Stores are reached through fsspec (``s3fs`` for ``s3://``, gcsfs's JSON-API file system for ``gs://``, ``adlfs``
for ``az://``), zarr arrays through zarr's own :class:`zarr.storage.FsspecStore`; every process (each Dask
worker too) opens its own. A store whose library is not installed, or that does not answer, is refused with one
line naming the location and what to do (:func:`missing_library`, :func:`store_error`). Credentials and the
endpoint come only from the store library's standard chains (S3: ``AWS_ACCESS_KEY_ID``,
``AWS_SECRET_ACCESS_KEY``, ``AWS_SESSION_TOKEN``, ``AWS_PROFILE``, ``AWS_ENDPOINT_URL``, ``AWS_DEFAULT_REGION``,
the shared config files, an instance role; GCS: ``GOOGLE_APPLICATION_CREDENTIALS``, gcloud's default login, the
instance's service account, ``STORAGE_EMULATOR_HOST``; Azure: ``AZURE_STORAGE_CONNECTION_STRING``, or
``AZURE_STORAGE_ACCOUNT_NAME`` with ``AZURE_STORAGE_ACCOUNT_KEY``, ``AZURE_STORAGE_SAS_TOKEN`` or a managed
identity): nothing here takes, stores or prints one.

Guarantees of :func:`publish_directory` (one scan's outputs under ``<out>/<scan>/``), on S3, GCS and Azure alike
(each store's requests: :mod:`mpi_lidar.storage._conditional`):

- Each object appears whole or not at all (one PUT or upload each; no store shows a partial object).
- The outputs are published by their manifest (:data:`~mpi_lidar.storage.manifest.MANIFEST_FILE`, the size and
  SHA-256 of every file), written last with a conditional create (``If-None-Match: *``; on GCS
  ``ifGenerationMatch=0``): the folder's outputs exist, for every reader of this package (the re-run's skip,
  ``mpi-lidar verify``, the summary), only once the manifest does, and then every object it lists must have its
  size (the skip) and digest (``verify``).
  Objects under a folder with no manifest are never outputs: a killed batch leaves at most such objects,
  and the next run deletes them before it writes the folder again.
- Replacing published outputs first deletes the manifest (the folder is then unpublished), then the old
  objects, then uploads and publishes the new ones; a reader that read the old manifest before sees a digest
  that differs, never a mix passed off as whole.
- Two writers cannot both publish one folder: the second conditional create is refused (one error line).
  One batch at a time holds the output location (:class:`ObjectOutputLock`).

:func:`publish_whole` (a scan or dataset store, a model directory) publishes by the one object its readers
open it by, written last with a conditional create: the store's root ``zarr.json``, the model's ``card.json``.

Not guaranteed: durability beyond the store's own, a reader that reads the objects without their manifest, and
GCS's zonal (Rapid) buckets, which gcsfs reaches over gRPC only.
"""

from __future__ import annotations

import json
import os
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, suppress
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any, cast

from mpi_lidar.errors import MpiLidarError, StoreError
from mpi_lidar.locations import Location
from mpi_lidar.storage import _conditional
from mpi_lidar.storage._stores import REACHED_BY, STORE_LIBRARIES, asynchronous_filesystem, filesystem_class
from mpi_lidar.storage.integrity import MAX_METADATA_BYTES, IntegrityError
from mpi_lidar.storage.manifest import MANIFEST_FILE, manifest_entries
from mpi_lidar.storage.publication import LOCK_FILE, OutputLock, counted_hold

if TYPE_CHECKING:
    from fsspec import AbstractFileSystem
    from zarr.storage import FsspecStore

WRITABLE_SCHEMES = ("s3", "gs", "az")
# A lock whose holder has not renewed it for this long is taken over (a holder on this host that is gone at once).
LOCK_LEASE_S = 60.0
_RENEW_EVERY_S = LOCK_LEASE_S / 4


def filesystem(where: Location) -> AbstractFileSystem:
    """The fsspec file system of an object-store location (one per process and options, fsspec's cache);
    listings are not cached, so every listing sees what other processes published."""
    try:
        return filesystem_class(where.scheme)(**storage_options(where))
    except ImportError:
        raise missing_library(where) from None


def missing_library(where: Location) -> MpiLidarError:
    """One line for a store whose fsspec library is not installed: which, and how to get it."""
    library = STORE_LIBRARIES.get(where.scheme, "an fsspec implementation")
    return MpiLidarError(f"{where}: {where.scheme}:// is reached through the {library} package, which is not "
                         f"installed; install it (pip install {library}, on every Dask worker too)")


# s3fs asks an object's size (a HEAD request) before every whole read, to split one larger than its block
# (50 MiB) into concurrent ranged reads. Chunks, manifests and metadata are far smaller, so that would double the
# requests of every read; zarr reads a store's chunks concurrently itself.
_SCHEME_OPTIONS: dict[str, dict[str, object]] = {"s3": {"max_concurrency": 1}}


def storage_options(where: Location) -> dict[str, object]:
    """The options every file system and zarr store of ``where``'s scheme is opened with: listings never cached
    (each sees what other processes published), whole objects read in one request."""
    return {"use_listings_cache": False, **_SCHEME_OPTIONS.get(where.scheme, {})}


def zarr_store(where: Location, read_only: bool = True) -> str | FsspecStore:
    """What ``zarr.open_group(store=...)`` takes for ``where``: the path, or zarr's FsspecStore on it."""
    if where.is_local:
        return where.path
    from zarr.storage import FsspecStore

    fs = filesystem(where)  # refused with one line where its library is not installed
    return FsspecStore(fs=asynchronous_filesystem(where.scheme, fs, storage_options(where)), path=where.path,
                       read_only=read_only)


def store_error(where: Location, exc: BaseException, doing: str) -> MpiLidarError:
    """One line for a failed store operation, naming the location, never the request (no credential)."""
    reason = type(exc).__name__ if isinstance(exc, FileNotFoundError | PermissionError) else (
        str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__)
    return StoreError(f"cannot {doing} {where} ({reason}); check the URL, "
                      f"{REACHED_BY.get(where.scheme, 'the store and its credentials')}")


def list_files(where: Location) -> dict[str, int]:
    """Every object below ``where`` (relative POSIX path -> size), one listing; metadata objects over
    :data:`~mpi_lidar.storage.integrity.MAX_METADATA_BYTES` are refused like a local store's."""
    fs = filesystem(where)
    try:
        found = _find_below(fs, where)
    except Exception as exc:  # botocore raises many types
        raise store_error(where, exc, "list") from None
    files: dict[str, int] = {}
    prefix = where.path.rstrip("/") + "/"
    for key, info in found.items():
        key = key.removeprefix(f"{where.scheme}://")
        if not key.startswith(prefix) or key == prefix or info.get("type") == "directory":
            continue
        relative, size = key[len(prefix):], int(info.get("size") or 0)
        if PurePosixPath(relative).name == "zarr.json" and size > MAX_METADATA_BYTES:
            raise IntegrityError(f"{where}: {relative} takes {size:,} bytes, more than the {MAX_METADATA_BYTES:,} a "
                                 "store's metadata may; the store is damaged: restore or regenerate it")
        files[relative] = size
    return files


def _find_below(fs: AbstractFileSystem, where: Location) -> dict[str, dict[str, Any]]:
    """fsspec's ``find`` of the objects below ``where``: on S3 as the keys under the prefix ``<name>/`` of its
    parent, one listing even where there are none (``find(path)`` would then ask whether ``path`` names an object:
    a HEAD and a second listing, for every output folder not yet written)."""
    parent, _, name = where.path.rstrip("/").rpartition("/")
    if where.scheme != "s3" or not parent:
        return cast("dict[str, dict[str, Any]]", fs.find(where.path, detail=True))
    return cast("dict[str, dict[str, Any]]", fs.find(parent, prefix=f"{name}/", detail=True))


def exists(where: Location) -> bool:
    """Whether an object (or a prefix holding objects) is at ``where``."""
    fs = filesystem(where)
    try:
        return bool(fs.exists(where.path))
    except Exception as exc:
        raise store_error(where, exc, "reach") from None


def read_bytes(where: Location, max_bytes: int = MAX_METADATA_BYTES) -> bytes | None:
    """An object's bytes (at most ``max_bytes``, else refused); None if it does not exist."""
    fs = filesystem(where)
    try:
        if fs.size(where.path) > max_bytes:
            raise IntegrityError(f"{where} takes more than {max_bytes:,} bytes; it is not ours")
        return bytes(fs.cat_file(where.path))
    except FileNotFoundError:
        return None
    except StoreError:
        raise
    except Exception as exc:
        raise store_error(where, exc, "read") from None


def check_writable(where: Location) -> None:
    """Refuse, with one line, a store the tool cannot publish into: publication needs a conditional create and
    overwrite (:mod:`mpi_lidar.storage._conditional`), which only the stores of :data:`WRITABLE_SCHEMES` offer."""
    if where.scheme not in WRITABLE_SCHEMES:
        raise MpiLidarError(f"{where}: writing to {where.scheme}:// is not supported (only "
                            f"{', '.join(s + '://' for s in WRITABLE_SCHEMES)}); write the outputs to one or a path")


def write_object(where: Location, data: bytes, *, create: bool = False, if_match: str | None = None) -> str:
    """Put one object (whole or not at all); ``create``: only if none is there (``If-None-Match: *``);
    ``if_match``: only over the object of that version (S3's and Azure's ETag, GCS's generation). A refused
    condition is :class:`FileExistsError`. Returns the new object's version."""
    check_writable(where)
    fs = filesystem(where)
    try:
        return _conditional.put(fs, where.scheme, where.path, data, create=create, if_match=if_match)
    except FileExistsError:
        raise FileExistsError(str(where)) from None
    except Exception as exc:
        raise store_error(where, exc, "write") from None


def remove_prefix(where: Location) -> None:
    """Delete every object below ``where``, the manifest first (so the folder is unpublished before anything
    it lists goes)."""
    check_writable(where)
    fs = filesystem(where)
    found = list_files(where)  # nothing there (a folder never written): no deletion asked
    if MANIFEST_FILE in found:
        try:
            fs.rm_file(f"{where.path}/{MANIFEST_FILE}")
        except FileNotFoundError:
            pass
        except Exception as exc:
            raise store_error(where, exc, "unpublish") from None
    keys = [f"{where.path}/{name}" for name in found if name != MANIFEST_FILE]
    if keys:
        try:
            fs.rm(keys)
        except Exception as exc:
            raise store_error(where, exc, "clear") from None


def upload_files(local_dir: Path, where: Location, skip: tuple[str, ...] = ()) -> list[str]:
    """Put every file under ``local_dir`` (but ``skip``) below ``where``, each a whole object; their names."""
    check_writable(where)
    fs = filesystem(where)
    names = sorted(p.relative_to(local_dir).as_posix() for p in local_dir.rglob("*") if p.is_file())
    names = [n for n in names if n not in skip]
    try:
        fs.put([str(local_dir / n) for n in names], [f"{where.path}/{n}" for n in names])
    except Exception as exc:
        raise store_error(where, exc, "upload to") from None
    return names


def publish_directory(local_dir: Path, where: Location) -> list[str]:
    """Publish the outputs built in ``local_dir`` (sealed: its manifest written) at ``where``, manifest last by
    a conditional create (see the module docstring); the names uploaded. Refused with one line if another
    writer published there meanwhile."""
    manifest = local_dir / MANIFEST_FILE
    remove_prefix(where)
    names = upload_files(local_dir, where, skip=(MANIFEST_FILE,))
    if manifest.is_file():
        try:
            write_object(where.joinpath(MANIFEST_FILE), manifest.read_bytes(), create=True)
        except FileExistsError:
            raise MpiLidarError(f"{where} was published by another writer while this one wrote it; its outputs are "
                                "that writer's: run one batch per output location") from None
        names.append(MANIFEST_FILE)
    return names


def publish_report(local_dir: Path, where: Location, marker: str) -> None:
    """Publish a report folder built in ``local_dir`` at ``where``, its ``marker`` object last by a conditional
    create: a previous report there (one with its marker) is replaced, as on disk; a prefix that holds anything
    else is refused with one line, and nothing is written."""
    found = list_files(where)
    if found and marker not in found:
        raise MpiLidarError(f"{where} holds {len(found)} objects that are not a report of ours; give another --out "
                            "(nothing was written)")
    if found:
        remove_prefix(where)
    publish_whole(local_dir, where, marker)


def publish_store(local_store: Path, where: Location) -> None:
    """Publish a Zarr store built in ``local_store`` at ``where``, its root ``zarr.json`` last
    (:func:`publish_whole`): the store exists for every reader (which opens it by that object) only once whole."""
    publish_whole(local_store, where, "zarr.json")


def publish_whole(local_dir: Path, where: Location, commit: str) -> None:
    """Publish the files built in ``local_dir`` at ``where``: every object but ``commit``, then ``commit`` last
    by a conditional create, so what readers open by that object (a store by its root metadata, a model by its
    card) exists only once whole, and never over one there. Objects a killed publication left (all but
    ``commit``) are written over. Refused with one line if ``commit`` is there already."""
    upload_files(local_dir, where, skip=(commit,))
    try:
        write_object(where.joinpath(commit), (local_dir / commit).read_bytes(), create=True)
    except FileExistsError:
        raise MpiLidarError(f"{where} already exists (written meanwhile by another process); remove it to write it "
                            "again") from None


def published_damage(where: Location) -> str | None:
    """None where ``where`` is published (its manifest there) and every object it lists is there with its size
    (one listing and one read: a resume checks manifests, not bytes); else why not."""
    try:
        text = read_bytes(where.joinpath(MANIFEST_FILE))
        if text is None:
            return f"{where}: not published (no manifest {MANIFEST_FILE})"
        listed = manifest_entries(text, str(where))
        present = list_files(where)
    except StoreError as exc:
        return str(exc).splitlines()[0]
    for name, entry in sorted(listed.items()):
        if present.get(name) != entry["bytes"]:
            return f"{where}: {name} is missing or not of the {entry['bytes']:,} bytes written"
    return None


def verify_published(where: Location) -> list[str]:
    """Every object the manifest at ``where`` lists, present with its size and SHA-256 (each read once); the
    names. A missing manifest or a differing object is an :class:`IntegrityError` naming it."""
    import hashlib

    damage = published_damage(where)
    if damage is not None:
        raise IntegrityError(f"{damage}; correct the scan again")
    text = read_bytes(where.joinpath(MANIFEST_FILE)) or b""
    listed = manifest_entries(text, str(where))
    fs = filesystem(where)
    for name, entry in sorted(listed.items()):
        digest = hashlib.sha256()
        try:
            with fs.open(f"{where.path}/{name}", "rb") as file:
                while block := file.read(2**22):
                    digest.update(block)
        except Exception as exc:
            raise store_error(where.joinpath(name), exc, "read") from None
        if digest.hexdigest() != entry["sha256"]:
            raise IntegrityError(f"{where}: {name} is not the object written there (edited or replaced); correct "
                                 "the scan again to restore it")
    return sorted(listed)


class ObjectOutputLock(OutputLock):
    """An output prefix in an object store, held by the object ``<out>/`` :data:`LOCK_FILE`.

    Taken by a conditional create (``If-None-Match: *``); the object names its holder (process, host, start)
    and the time it was last renewed, which a thread of the holder does every :data:`LOCK_LEASE_S` / 4
    seconds. A lock not renewed for :data:`LOCK_LEASE_S`, or whose holder on this host is no longer running,
    is stale: it is taken over by a conditional overwrite of that very object (``If-Match`` its ETag; on GCS
    ``ifGenerationMatch`` its generation), so of two batches taking it over at once only one succeeds. Renewals
    are conditional overwrites of the version the last one wrote. Released by deleting it. Nested holds in one
    thread are one hold. There is nothing to clean up in a folder (:meth:`remove_interrupted`): objects a killed
    batch left unpublished are replaced where their scan is written again.
    """

    def __init__(self, out: Location):
        self.out = out
        self.lock = out.joinpath(LOCK_FILE)

    def hold(self) -> AbstractContextManager[None]:
        return self._hold()

    def remove_interrupted(self, folder: PurePosixPath) -> None:
        return None

    @contextmanager
    def _hold(self) -> Iterator[None]:
        with counted_hold(self.lock.url) as outermost:
            if not outermost:
                yield
                return
            etag = self._take()
            stop = threading.Event()
            renewer = threading.Thread(target=self._renew, args=(etag, stop), daemon=True)
            renewer.start()
            try:
                yield
            finally:
                stop.set()
                renewer.join()
                self._release()

    def _record(self) -> bytes:
        started = time.strftime("%Y-%m-%d %H:%M:%S %Z")
        return json.dumps({"holder": f"pid {os.getpid()} on {socket.gethostname()}, started {started}",
                           "pid": os.getpid(), "host": socket.gethostname(), "renewed": time.time()}).encode()

    def _take(self) -> str:
        for _ in range(5):
            try:
                return write_object(self.lock, self._record(), create=True)
            except FileExistsError:
                pass
            info, etag = self._current()
            if info is None:
                continue  # released meanwhile: try again
            if not _stale(info):
                raise MpiLidarError(f"output location {self.out} is being written by another correct run "
                                    f"({info.get('holder', 'unnamed')}); wait for it to finish or choose another --out")
            try:
                return write_object(self.lock, self._record(), if_match=etag)
            except FileExistsError:
                continue  # another batch took it over first
        raise MpiLidarError(f"cannot lock output location {self.out}: its lock keeps changing; choose another --out")

    def _current(self) -> tuple[dict[str, object] | None, str]:
        fs = filesystem(self.lock)
        try:
            etag = _conditional.version(self.lock.scheme, fs.info(self.lock.path))
            data = json.loads(fs.cat_file(self.lock.path))
        except FileNotFoundError:
            return None, ""
        except ValueError:
            return {"renewed": 0.0}, etag  # not a lock we wrote whole: stale
        return (data if isinstance(data, dict) else {"renewed": 0.0}), etag

    def _renew(self, etag: str, stop: threading.Event) -> None:
        while not stop.wait(_RENEW_EVERY_S):
            try:
                etag = write_object(self.lock, self._record(), if_match=etag)
            except (FileExistsError, MpiLidarError):
                return  # taken over or unreachable: the batch's own writes will say so

    def _release(self) -> None:
        with suppress(Exception):  # gone already, or unreachable: it goes stale
            filesystem(self.lock).rm_file(self.lock.path)


def _stale(info: dict[str, object]) -> bool:
    renewed = info.get("renewed")
    if not isinstance(renewed, int | float) or time.time() - renewed > LOCK_LEASE_S:
        return True
    pid = info.get("pid")
    if info.get("host") == socket.gethostname() and isinstance(pid, int):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        except OSError:
            return False
    return False

