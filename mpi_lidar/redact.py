"""Secrets never leave the process: passwords in URLs and connection strings are masked in every message.

Credentials come only from the environment (``MPI_LIDAR_STORAGE_URL``, ``PGPASSWORD``, ``~/.pgpass``) or the
command line (``--storage``, ``--scheduler``); never from a Prefect flow's parameters, which Prefect stores in
clear (``flows/tune.py`` refuses a ``storage`` parameter that carries one). A URL can carry a password in its user part
(``postgresql+psycopg://user:secret@host/db``, ``tcp://user:secret@host:8786``, ``tls://...``), %-encoded or
not, with an unencoded ``@``, ``:`` or ``/`` inside it (the user part ends at the last ``@`` that a host
follows); as a query parameter that libpq accepts (``?password=secret``, ``&sslpassword=...``); as a
``key=value`` option of a libpq connection string (``host=h password=secret``) or a mapping's
``'password': 'secret'``; an Azure Storage connection string's ``AccountKey=...;`` or
``SharedAccessSignature=...;``, a SAS token's ``sig=...``, ``account_key``/``sas_token``/``client_secret``
options and the ``AZURE_STORAGE_*`` variables that hold a key (a ``key=value`` ends at ``;``, ``&``, a comma or
whitespace, so an ``@``, ``:``, ``/``, ``+`` or ``=`` in a key is masked with it). ``passfile`` and ``sslkey``
name files whose paths say where a secret lives. :func:`redact` masks all of them, wherever they appear in a
text, and every other occurrence of a password it found there (as written and %-decoded). Masking errs on the
side of hiding: an ``@`` in a URL's path or query after the host masks up to it. A password with whitespace in
it must be %-encoded to be found.

:func:`install_log_redaction` masks every log record of the process the same way (messages, arguments and
tracebacks), whichever library logs it.
"""

from __future__ import annotations

import logging
import re
import traceback
from collections.abc import Callable
from urllib.parse import unquote

MASK = "***"
SECRET_KEYS = ("password", "passwd", "pwd", "passfile", "sslpassword", "sslkey", "token", "secret", "api_key",
               # Azure Storage: a connection string's AccountKey and SharedAccessSignature, a SAS's signature (sig),
               # adlfs's options and the AZURE_STORAGE_* variables that carry a key, a SAS or a client secret.
               "accountkey", "account_key", "sharedaccesssignature", "sig", "sas_token", "client_secret",
               "azure_storage_account_key", "azure_storage_sas_token", "azure_storage_client_secret",
               "azure_storage_connection_string")
# Where a password is also searched for elsewhere in the text: shorter ones would mask ordinary words.
_MIN_REPEATED_SECRET = 3

_SCHEME = re.compile(r"(?<![A-Za-z0-9+.-])[A-Za-z][A-Za-z0-9+.-]*://")
# What follows the '@' that ends a URL's user part: a host (a name, an IPv4 address, a bracketed IPv6 address,
# or nothing, as in postgresql://u:p@/db?host=/run/postgresql), an optional port, then the end of the
# authority, or of the URL within a message (a quote, a bracket, a comma, a colon).
_HOST_TAIL = re.compile(r"(?:\[[0-9A-Za-z:.%]*\]|[A-Za-z0-9._~-]*)(?::[0-9]*)?(?=$|[/?#'\"`)\]}>,;:])")
_KEYS = "|".join(SECRET_KEYS)
_KEY_VALUE = re.compile(
    r"(?P<head>(?<![A-Za-z0-9_])(?:" + _KEYS + r")\s*=\s*)(?P<secret>'[^']*'|\"[^\"]*\"|[^&\s;,)'\"]+)",
    re.IGNORECASE)
_MAPPING = re.compile(
    r"(?P<head>(?P<q>['\"])(?:" + _KEYS + r")(?P=q)\s*:\s*)(?P<secret>'[^']*'|\"[^\"]*\")", re.IGNORECASE)


def _user_part_end(authority_and_rest: str) -> int:
    """The index of the '@' that ends a URL's user part (the last one a host follows), or -1."""
    at = authority_and_rest.rfind("@")
    while at >= 0:
        if _HOST_TAIL.match(authority_and_rest, at + 1):
            return at
        at = authority_and_rest.rfind("@", 0, at)
    return -1


def _mask_urls(text: str, secrets: list[str]) -> str:
    out: list[str] = []
    position = 0
    for match in _SCHEME.finditer(text):
        if match.start() < position:  # inside the user part of a URL already masked
            continue
        start = match.end()
        token_end = re.search(r"\s|$", text[start:])
        end = start + (token_end.start() if token_end else len(text) - start)
        token = text[start:end]
        at = _user_part_end(token)
        if at < 0:
            continue
        user, colon, password = token[:at].partition(":")
        if not colon:
            continue
        secrets += [password, unquote(password)]
        out += [text[position:start], user, ":", MASK]
        position = start + at
    out.append(text[position:])
    return "".join(out)


def _mask_pattern(pattern: re.Pattern[str], text: str, secrets: list[str]) -> str:
    def mask(m: re.Match[str]) -> str:
        secret = m["secret"].strip("'\"")
        secrets.extend([secret, unquote(secret)])
        return m["head"] + MASK

    return pattern.sub(mask, text)


def redact(text: str) -> str:
    """``text`` with every password-like value in URLs and connection strings replaced by ``***``."""
    secrets: list[str] = []
    text = _mask_urls(text, secrets)
    text = _mask_pattern(_KEY_VALUE, text, secrets)
    text = _mask_pattern(_MAPPING, text, secrets)
    for secret in sorted({s for s in secrets if len(s) >= _MIN_REPEATED_SECRET and s != MASK}, key=len,
                         reverse=True):
        text = text.replace(secret, MASK)
    return text


def split_user_part(url: str) -> tuple[str, str, str]:
    """``(scheme://, user part, rest)`` of a URL; the user part (``user:password``, %-encoded or not, with an
    unencoded ``@``, ``:`` or ``/`` in it) is empty where the URL has none. The same rule as :func:`redact`: the
    user part ends at the last ``@`` that a host follows."""
    match = _SCHEME.match(url)
    if match is None:
        return "", "", url
    rest = url[match.end():]
    at = _user_part_end(rest)
    return (match.group(0), "", rest) if at < 0 else (match.group(0), rest[:at], rest[at + 1:])


def carries_secret(text: str) -> bool:
    """Whether ``text`` holds a password or another secret :func:`redact` would mask."""
    return redact(text) != text


class _Redacting:
    """A log-record factory that masks what :func:`redact` masks, in the message and the traceback."""

    def __init__(self, inner: Callable[..., logging.LogRecord]) -> None:
        self.inner = inner

    def __call__(self, *args: object, **kwargs: object) -> logging.LogRecord:
        record = self.inner(*args, **kwargs)
        try:
            message = record.getMessage()
        except Exception:  # a record whose arguments do not fit its format: logging reports it itself
            return record
        record.msg, record.args = redact(message), ()
        if record.exc_info and record.exc_info[0] is not None:
            record.exc_text = redact("".join(traceback.format_exception(*record.exc_info)).rstrip("\n"))
        if record.stack_info:
            record.stack_info = redact(record.stack_info)
        return record


def install_log_redaction() -> None:
    """Mask secrets in every log record this process creates from now on, whichever logger (idempotent)."""
    factory = logging.getLogRecordFactory()
    if not isinstance(factory, _Redacting):
        logging.setLogRecordFactory(_Redacting(factory))
