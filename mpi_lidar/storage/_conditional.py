"""Conditional writes in each object store, and the version token a conditional overwrite names.

Publication (:mod:`mpi_lidar.storage.objects`) needs two writes that each store performs atomically, in one
request: a create only where no object is, and an overwrite only of the version read.

- S3: ``PUT`` with ``If-None-Match: *`` (s3fs's ``mode="create"``); ``PUT`` with ``If-Match: <ETag>``.
- GCS: a multipart upload with ``ifGenerationMatch=0`` (gcsfs's ``mode="create"``); the same with
  ``ifGenerationMatch=<generation>`` (made here: gcsfs's ``pipe_file`` takes no generation).
- Azure Blob: Put Blob with ``If-None-Match: *`` (adlfs's ``mode="create"``, azure-storage-blob's
  ``upload_blob(overwrite=False)``); Put Blob with ``If-Match: <ETag>`` (``match_condition=IfNotModified``).

A refused condition is a :class:`FileExistsError` (S3 and GCS answer 412 Precondition Failed, or 409 for two
conditional writes of one S3 key at once; Azure 409 BlobAlreadyExists or 412 ConditionNotMet). The version token
is the S3 or Azure ETag and the GCS generation (a GCS ETag may name the content, not the write). Each is tested
against a server started by the tests on 127.0.0.1 (moto's S3, fake-gcs-server, Azurite), not against the cloud
services themselves.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

if TYPE_CHECKING:
    from fsspec import AbstractFileSystem

# The key of the version token in a store's object information (fsspec's ``info``) and in its write's response.
_VERSION_KEY = {"s3": "ETag", "gs": "generation", "az": "etag"}
# gcsfs's multipart boundary, as its own simple upload writes it: a line no JSON metadata holds.
_BOUNDARY = "==0=="


def put(fs: AbstractFileSystem, scheme: str, path: str, data: bytes, *, create: bool = False,
        if_match: str | None = None) -> str:
    """Write ``data`` at ``path`` (one request: whole or not at all); ``create``: only where no object is;
    ``if_match``: only over the object of that version token. The new object's version token. A refused
    condition raises :class:`FileExistsError`, any other failure the store library's own exception."""
    if scheme == "gs" and if_match is not None:
        return _gcs_overwrite(fs, path, data, if_match)
    kwargs: dict[str, object] = {"mode": "create"} if create else {}
    if if_match is not None:
        kwargs.update(_if_match_options(scheme, if_match))
    try:
        response = fs.pipe_file(path, data, **kwargs)
    except Exception as exc:
        if precondition_failed(exc):
            raise FileExistsError(path) from None
        raise
    return _token(scheme, response)


def version(scheme: str, info: dict[str, Any]) -> str:
    """The version token of an object from its information (fsspec's ``info``); empty where the store gave none."""
    return str(info.get(_VERSION_KEY.get(scheme, "ETag")) or "")


def precondition_failed(exc: BaseException) -> bool:
    """Whether a store refused a conditional write: S3's 412 PreconditionFailed or 409
    ConditionalRequestConflict (botocore's error text), gcsfs's and adlfs's :class:`FileExistsError`, Azure's 412
    ConditionNotMet (azure-core's ``status_code``)."""
    if isinstance(exc, FileExistsError) or getattr(exc, "status_code", None) == 412:
        return True
    text = f"{type(exc).__name__} {exc}"
    # Matched by the error's name, never by a bare "412": an object's own key may hold that number.
    return "PreconditionFailed" in text or "ConditionalRequestConflict" in text


def _if_match_options(scheme: str, token: str) -> dict[str, object]:
    if scheme == "az":
        from azure.core import MatchConditions

        return {"etag": token, "match_condition": MatchConditions.IfNotModified}
    return {"IfMatch": token}


def _token(scheme: str, response: object) -> str:
    return version(scheme, response) if isinstance(response, dict) else ""


def _gcs_overwrite(fs: AbstractFileSystem, path: str, data: bytes, generation: str) -> str:
    """gcsfs's one-request (multipart) upload with ``ifGenerationMatch=<generation>``, which its ``pipe_file``
    does not take; the new generation."""
    bucket, key, _ = fs.split_path(path)
    head = (f"--{_BOUNDARY}\nContent-Type: application/json; charset=UTF-8\n\n{json.dumps({'name': key})}\n"
            f"--{_BOUNDARY}\nContent-Type: application/octet-stream\n\n").encode()
    response = fs.call("POST", f"{fs._location}/upload/storage/v1/b/{quote(bucket, safe='')}/o",
                       uploadType="multipart", ifGenerationMatch=generation, json_out=True,
                       headers={"Content-Type": f'multipart/related; boundary="{_BOUNDARY}"'},
                       data=head + data + f"\n--{_BOUNDARY}--".encode())
    return _token("gs", response)
