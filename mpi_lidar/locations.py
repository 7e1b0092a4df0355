"""Where the tool reads and writes: a local path or an object-store URL, parsed once and shown without secrets.

:func:`location` turns what a user gives (``/data/scans``, ``scans/``, ``file:///data/scans``,
``s3://bucket/archive/``, ``gs://bucket/x``, ``az://container/x``) into a :class:`Location`: whether it is on
the local file system, its child locations, and its text for messages. An object-store URL never carries a
credential: one with a user part (``s3://key:secret@bucket/...``) is refused with one line that shows it
masked. Credentials come only from the standard chains of the store's library (for S3: the environment's
``AWS_ACCESS_KEY_ID``/``AWS_SECRET_ACCESS_KEY``/``AWS_SESSION_TOKEN``, ``AWS_PROFILE`` and the shared files,
an instance role; the endpoint from ``AWS_ENDPOINT_URL``; for GCS ``GOOGLE_APPLICATION_CREDENTIALS`` and
gcloud's login; for Azure ``AZURE_STORAGE_CONNECTION_STRING`` or ``AZURE_STORAGE_ACCOUNT_NAME`` with its key, a
SAS or a managed identity), so no URL the tool stores or prints holds one. The Azure account is not part of an
``az://`` URL either: ``abfs://container@account.dfs.core.windows.net/x`` is refused with one line saying so.
:func:`display_url` shows any other URL the tool takes (a scheduler's, a database's) with its password masked;
:func:`driver_url` percent-encodes what cannot stand unencoded in a URL's user part before a driver parses it.
"""

from __future__ import annotations

import posixpath
import re
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote, unquote

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.redact import redact, split_user_part

OBJECT_STORE_SCHEMES = ("s3", "gs", "az")
# Other spellings fsspec knows for the same stores.
_ALIASES = {"s3a": "s3", "gcs": "gs", "abfs": "az", "abfss": "az"}
# The host of adlfs's ``abfs://container@account.dfs.core.windows.net/path`` form, which names the account.
_AZURE_HOST = re.compile(r"[a-z0-9]{3,24}\.(?:blob|dfs)\.core\.windows\.net", re.IGNORECASE)


@dataclass(frozen=True)
class Location:
    """A local path (``scheme`` empty) or an object in a store: ``scheme`` (``s3``, ``gs``, ``az``) and
    ``path`` (``bucket/key/...``, no leading or trailing ``/``). Never holds a credential."""

    scheme: str
    path: str

    @property
    def is_local(self) -> bool:
        """Whether this is a path on the local file system (given as a path or a ``file://`` URL)."""
        return not self.scheme

    @property
    def url(self) -> str:
        """The path, or ``scheme://bucket/key``: what fsspec and zarr open."""
        return self.path if self.is_local else f"{self.scheme}://{self.path}"

    @property
    def name(self) -> str:
        """The last component (a scan store's or a folder's name)."""
        return posixpath.basename(self.path) if not self.is_local else Path(self.path).name

    @property
    def parent(self) -> Location:
        if self.is_local:
            return Location("", str(Path(self.path).parent))
        return Location(self.scheme, posixpath.dirname(self.path) or self.path)

    def joinpath(self, *names: str) -> Location:
        """The location of ``names`` (``/``-separated relative paths) below this one."""
        parts = [p for name in names for p in name.split("/") if p]
        if self.is_local:
            return Location("", str(Path(self.path).joinpath(*parts)))
        return Location(self.scheme, posixpath.join(self.path, *parts))

    def local_path(self) -> Path:
        """The local path; refused for a location in an object store."""
        if not self.is_local:
            raise MpiLidarError(f"{self} is in an object store, not on the local file system")
        return Path(self.path)

    def __str__(self) -> str:
        return self.url

    def __truediv__(self, name: str) -> Location:
        return self.joinpath(name)


def is_url(text: str | Path) -> bool:
    """Whether ``text`` names an object store or a ``file://`` URL rather than a plain path."""
    return isinstance(text, str) and bool(split_user_part(text)[0])


def location(given: str | Path | Location) -> Location:
    """Parse a path or URL; an unsupported scheme or a URL carrying a credential is refused with one line."""
    if isinstance(given, Location):
        return given
    if isinstance(given, Path):
        return Location("", str(given))
    scheme_sep, user, rest = split_user_part(given)
    if not scheme_sep:
        return Location("", given)
    scheme = scheme_sep.removesuffix("://").lower()
    scheme = _ALIASES.get(scheme, scheme)
    if user and scheme == "az" and ":" not in user and _AZURE_HOST.fullmatch(rest.split("/", 1)[0]):
        raise MpiLidarError(f"{redact(given)} names the account in the URL; give az://{user}/<path> and the account "
                            "through AZURE_STORAGE_CONNECTION_STRING or AZURE_STORAGE_ACCOUNT_NAME")
    if user and ("/" not in user.split(":", 1)[0]):
        raise MpiLidarError(f"{redact(given)} carries a credential in the URL; give it through the environment "
                            "(AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY, AWS_PROFILE, "
                            "GOOGLE_APPLICATION_CREDENTIALS, AZURE_STORAGE_*) and name the store without it")
    if user:  # an '@' in the path, not a user part
        rest = f"{user}@{rest}"
    if scheme == "file":
        return Location("", rest)
    if scheme not in OBJECT_STORE_SCHEMES:
        raise MpiLidarError(f"{redact(given)}: the scheme {scheme}:// is not a store the tool reads or writes; "
                            f"give a path or a URL of {', '.join(s + '://' for s in OBJECT_STORE_SCHEMES)}")
    path = posixpath.normpath("/" + rest).strip("/")
    if not path or path == ".":
        raise MpiLidarError(f"{redact(given)} names no bucket; give {scheme}://bucket/prefix")
    return Location(scheme, path)


def display_url(url: str) -> str:
    """Any URL the tool takes (a store, a scheduler, a database) as messages, logs and reports show it:
    passwords masked (:func:`mpi_lidar.redact.redact`)."""
    return redact(url)


def driver_url(url: str) -> str:
    """A URL (a database's) as a driver's parser must read it: its user name and password percent-encoded.

    A password may hold ``@``, ``:``, ``/``, ``?`` or ``#`` as the user typed it; a driver's parser splits the URL
    at the first ``@`` and would take the password's tail for the host (and print it). The user part ends at the
    last ``@`` that a host follows (:func:`mpi_lidar.redact.split_user_part`, as :func:`display_url` masks it);
    what was percent-encoded already stays as it was.
    """
    scheme_sep, user, rest = split_user_part(url)
    if not scheme_sep or not user:
        return url
    name, colon, password = user.partition(":")
    encoded = quote(unquote(name), safe="") + (colon and ":" + quote(unquote(password), safe=""))
    return f"{scheme_sep}{encoded}@{rest}"
