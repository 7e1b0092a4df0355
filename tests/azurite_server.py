"""Azurite's Azure Blob server for the az:// tests: a subprocess on a free port of 127.0.0.1, in memory, never a
public endpoint. ``make system-deps`` installs it into ``.tools/azurite`` (the Makefile's pinned version).

It serves Azurite's development account, whose name and key are published in Azure's documentation for exactly
this use (they open nothing else); :func:`azure_environment` points the standard variable at it.
"""

from __future__ import annotations

import socket
import subprocess
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from tests.environment import environment

AZURITE = Path(__file__).resolve().parents[1] / ".tools" / "azurite" / "node_modules" / ".bin" / "azurite-blob"
ACCOUNT = "devstoreaccount1"
ACCOUNT_KEY = "Eby8vdM02xNOcqFlqUwJPLlmEtlCDXJ1OUzFT50uSRZ6IFsuFq2UVErCz4I6tq/K1SZFPTOtr/KBHBeksoGMGw=="
AZURE_VARIABLES = ("AZURE_STORAGE_CONNECTION_STRING", "AZURE_STORAGE_ACCOUNT_NAME", "AZURE_STORAGE_ACCOUNT_KEY",
                   "AZURE_STORAGE_SAS_TOKEN", "AZURE_STORAGE_ANON")


@contextmanager
def azurite_server() -> Iterator[str]:
    """Inside: Azurite's Blob service running (in memory, telemetry off); its blob endpoint URL."""
    if not AZURITE.is_file():
        pytest.fail(f"Azurite is not installed ({AZURITE} is missing): run `make system-deps`", pytrace=False)
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with tempfile.TemporaryDirectory(prefix="azurite-") as workspace:
        # --skipApiVersionCheck: azure-storage-blob may speak a newer API version than this Azurite knows.
        server = subprocess.Popen(
            [str(AZURITE), "--blobHost", "127.0.0.1", "--blobPort", str(port), "--inMemoryPersistence",
             "--extentMemoryLimit", "256", "--skipApiVersionCheck", "--disableTelemetry", "--silent"],
            cwd=workspace, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        endpoint = f"http://127.0.0.1:{port}/{ACCOUNT}"
        try:
            _wait_until_listening(server, f"http://127.0.0.1:{port}/")
            yield endpoint
        finally:
            server.terminate()
            try:
                server.wait(timeout=10)
            except subprocess.TimeoutExpired:
                server.kill()
                server.wait()


def _wait_until_listening(server: subprocess.Popen[bytes], url: str, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if server.poll() is not None:
            error = server.stderr.read().decode(errors="replace") if server.stderr else ""
            raise RuntimeError(f"Azurite exited with status {server.returncode}: {error[-500:]}")
        try:
            urllib.request.urlopen(url, timeout=1).close()
            return
        except urllib.error.HTTPError:  # it answers (400 for a request naming no account): listening
            return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"Azurite did not listen on {url} within {timeout_s:.0f} s")


def connection_string(endpoint: str, key: str = ACCOUNT_KEY) -> str:
    """The connection string of the development account at ``endpoint`` (a blob endpoint URL)."""
    return f"DefaultEndpointsProtocol=http;AccountName={ACCOUNT};AccountKey={key};BlobEndpoint={endpoint};"


@contextmanager
def azure_environment(endpoint: str) -> Iterator[None]:
    """The standard variable ``AZURE_STORAGE_CONNECTION_STRING`` pointing at ``endpoint`` inside the block
    (processes started in it inherit it; the other ``AZURE_STORAGE_*`` variables unset), put back after it."""
    from adlfs import AzureBlobFileSystem

    with environment(AZURE_VARIABLES, {"AZURE_STORAGE_CONNECTION_STRING": connection_string(endpoint)},
                     AzureBlobFileSystem.clear_instance_cache):
        yield
