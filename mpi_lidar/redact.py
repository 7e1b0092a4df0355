"""Secrets never leave the process: passwords in URLs and connection strings are masked in every message.

Credentials come only from the environment or the command line (``MPI_LIDAR_STORAGE_URL``, ``--storage``).
A database URL can carry a password in its user part (``postgresql://user:secret@host/db``), as a query
parameter that libpq accepts (``?password=secret``, ``&sslpassword=...``), or as a ``key=value`` option of a
libpq connection string (``host=h password=secret``); ``passfile`` and ``sslkey`` name files whose paths say
where a secret lives. :func:`redact` masks all of them, wherever they appear in a text.
"""

from __future__ import annotations

import re

MASK = "***"
SECRET_KEYS = ("password", "passwd", "pwd", "passfile", "sslpassword", "sslkey", "token", "secret", "api_key")
_USER_PASSWORD = re.compile(r"(?P<head>[A-Za-z][A-Za-z0-9+.-]*://[^:/?#@\s]*:)(?P<secret>[^@\s]*)(?=@)")
_KEY_VALUE = re.compile(
    r"(?P<head>(?<![A-Za-z0-9_])(?:" + "|".join(SECRET_KEYS) + r")\s*=\s*)(?P<secret>'[^']*'|[^&\s;,)'\"]+)",
    re.IGNORECASE)


def redact(text: str) -> str:
    """``text`` with every password-like value in URLs and connection strings replaced by ``***``."""
    text = _USER_PASSWORD.sub(lambda m: m["head"] + MASK, text)
    return _KEY_VALUE.sub(lambda m: m["head"] + MASK, text)
