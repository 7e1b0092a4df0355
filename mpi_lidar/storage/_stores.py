"""Which library reaches each object store, where it finds the store and its credentials, and the file-system
classes opened for it (for the process's own calls, and asynchronous ones for zarr's stores)."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, cast

if TYPE_CHECKING:
    from fsspec import AbstractFileSystem

# The fsspec library of each store's scheme, and where that library finds the store and its credentials.
STORE_LIBRARIES = {"s3": "s3fs", "gs": "gcsfs", "az": "adlfs"}
REACHED_BY = {
    "s3": "the endpoint (AWS_ENDPOINT_URL) and the credentials (AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY, "
          "AWS_PROFILE or an instance role)",
    "gs": "the credentials (GOOGLE_APPLICATION_CREDENTIALS, gcloud's default login or the instance's service "
          "account)",
    "az": "the account and its credentials (AZURE_STORAGE_CONNECTION_STRING, or AZURE_STORAGE_ACCOUNT_NAME with "
          "AZURE_STORAGE_ACCOUNT_KEY, AZURE_STORAGE_SAS_TOKEN or a managed identity)",
}
# gcsfs's default file system first asks a gRPC control plane each bucket's layout (for zonal buckets): a request
# that fails, with a warning, on every operation wherever that plane is not reached. Its JSON-API file system is
# the one whose conditional writes are tested here.
_CLASSES = {"gs": ("gcsfs.core", "GCSFileSystem")}
_WRAPPED = ("gs", "az")


def filesystem_class(scheme: str) -> type[AbstractFileSystem]:
    """The fsspec file-system class of ``scheme``; :class:`ImportError` where its library is not installed."""
    import fsspec

    if scheme in _CLASSES:
        module, name = _CLASSES[scheme]
        return cast("type[AbstractFileSystem]", getattr(importlib.import_module(module), name))
    return cast("type[AbstractFileSystem]", fsspec.get_filesystem_class(scheme))


def asynchronous_filesystem(scheme: str, sync_fs: AbstractFileSystem, options: dict[str, object]
                            ) -> AbstractFileSystem:
    """The asynchronous file system zarr's FsspecStore needs. On S3 what ``FsspecStore.from_url`` makes; on GCS
    and Azure the process's file system ``sync_fs`` wrapped, because gcsfs's and adlfs's own asynchronous instances
    close their sessions at exit through a loop they do not run on and print a traceback after every command
    (fsspec/adlfs#495)."""
    if scheme in _WRAPPED:
        from fsspec.implementations.asyn_wrapper import AsyncFileSystemWrapper

        return AsyncFileSystemWrapper(sync_fs, asynchronous=True)
    return filesystem_class(scheme)(asynchronous=True, **options)
