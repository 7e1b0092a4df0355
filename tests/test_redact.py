"""Passwords are masked in every URL and connection-string form libpq accepts."""

from __future__ import annotations

import logging
import tempfile
from urllib.parse import quote

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mpi_lidar.learning.tune import masked
from mpi_lidar.redact import MASK, install_log_redaction, redact
from mpi_lidar.workflows.cluster import check_scheduler_address
from tests.cli_runner import assert_one_error_line, call_main

pytestmark = pytest.mark.unit

SECRET = "hunter2-Zq9"


@pytest.mark.parametrize("text", [
    f"postgresql://postgres:{SECRET}@127.0.0.1:5432/db",
    f"postgresql+psycopg://postgres@127.0.0.1/db?password={SECRET}",
    f"postgresql://postgres@127.0.0.1/db?sslmode=require&password={SECRET}&application_name=x",
    f"postgresql://postgres@127.0.0.1/db?PASSWORD={SECRET}",
    f"host=127.0.0.1 user=postgres password={SECRET} dbname=db",
    f"host=127.0.0.1 password='{SECRET}' dbname=db",
    f"postgresql://postgres@127.0.0.1/db?passfile=/home/{SECRET}/.pgpass",
    f"error: cannot reach Optuna storage postgresql://u:{SECRET}@h/db: connection refused",
])
def test_redact__masks_every_password_form(text):
    assert SECRET not in redact(text)
    assert "***" in redact(text)


def test_redact__leaves_urls_without_secrets_alone():
    for text in ("sqlite:///runs/quick/optuna.db", "postgresql://postgres@127.0.0.1:5432/db?sslmode=require",
                 "tcp://127.0.0.1:8786"):
        assert redact(text) == text


def test_masked__query_password_of_a_storage_url():
    assert SECRET not in masked(f"postgresql://postgres@127.0.0.1/db?password={SECRET}")


@given(st.text(alphabet=st.characters(whitelist_categories=("L", "N"), whitelist_characters="!$%^*-_+~"),
               min_size=1, max_size=30))
def test_redact__any_password_characters(tail):
    secret = f"Zq{tail}"  # a prefix that no fixed part of the URL contains
    for text in (f"postgresql://u:{secret}@h/db", f"postgresql://u@h/db?password={secret}"):
        assert secret not in redact(text)


# Every character a password may hold, the URL's own separators included; whitespace must be %-encoded.
PASSWORD_CHARACTERS = st.characters(blacklist_categories=("Z", "C"), blacklist_characters="\t\n\r ")
SCHEMES = ["postgresql", "postgresql+psycopg", "postgresql+psycopg2", "mysql+pymysql", "tcp", "tls", "https"]
HOSTS = ["127.0.0.1", "db.example.org", "[::1]", ""]


@settings(max_examples=300, deadline=None)
@given(tail=st.text(alphabet=PASSWORD_CHARACTERS, min_size=0, max_size=24), scheme=st.sampled_from(SCHEMES),
       host=st.sampled_from(HOSTS), port=st.sampled_from(["", ":5432", ":8786"]),
       rest=st.sampled_from(["", "/db", "/db?sslmode=require", "/db?application_name=x&connect_timeout=5"]),
       user=st.sampled_from(["postgres", "u", ""]), encode=st.booleans(),
       frame=st.sampled_from(["{}", "error: cannot reach {}: refused", "('{}')", "storage={} trials=3", "{}\n{}"]))
def test_redact__password_of_any_url_form_is_never_printed(tail, scheme, host, port, rest, user, encode, frame):
    """A password with '@', ':', '/', '%', '?', '#' in it, %-encoded or as typed, in any scheme and any message."""
    password = f"Zq{tail}"  # a prefix no fixed part of the text holds
    written = quote(password, safe="") if encode else password
    url = f"{scheme}://{user}:{written}@{host}{port}{rest}"
    masked = redact(frame.format(url, url))
    assert password not in masked and written not in masked
    assert f"{scheme}://{user}:{MASK}@" in masked
    if host:  # where the URL points stays readable
        assert f"@{host}{port}" in masked


@settings(max_examples=200, deadline=None)
@given(password=st.text(alphabet=st.characters(blacklist_categories=("Z", "C")), min_size=1, max_size=24),
       key=st.sampled_from(["password", "PASSWORD", "sslpassword"]))
def test_redact__query_parameter_passwords_percent_encoded(password, key):
    secret = f"Zq{password}"
    encoded = quote(secret, safe="")
    masked = redact(f"postgresql://u@h/db?sslmode=require&{key}={encoded}&application_name=x")
    assert encoded not in masked and secret not in masked
    assert "application_name=x" in masked


@pytest.mark.parametrize("text", [
    f"tcp://user:{SECRET}@127.0.0.1:1",
    f"tls://user:{SECRET}@scheduler.example.org:8786",
    f"postgresql+psycopg://postgres:{SECRET}@127.0.0.1:5432/db",
    f"postgresql://postgres:{quote(SECRET + '@x/y', safe='')}@127.0.0.1/db",
    f"postgresql://postgres:{SECRET}@tail@127.0.0.1/db",  # an unencoded '@': the tail is masked too
    f"postgresql://postgres:{SECRET}/with:slash@127.0.0.1/db",
    f"{{'password': '{SECRET}', 'user': 'postgres'}}",
    f'{{"password": "{SECRET}"}}',
])
def test_redact__every_form_named_in_the_issue(text):
    masked = redact(text)
    assert SECRET not in masked and "tail" not in masked and "slash" not in masked


def test_redact__decoded_password_elsewhere_in_the_text():
    url = f"postgresql://u:{quote(SECRET + '@', safe='')}@h/db"
    masked = redact(f"{url}: password authentication failed for {SECRET}@")
    assert SECRET not in masked


def test_install_log_redaction__masks_messages_arguments_and_tracebacks(caplog):
    install_log_redaction()
    install_log_redaction()  # idempotent
    logger = logging.getLogger("tests.redact")
    with caplog.at_level(logging.INFO, logger="tests.redact"):
        logger.info("connecting to %s", f"tcp://u:{SECRET}@h:1")
        try:
            raise ValueError(f"invalid address postgresql://u:{SECRET}@h/db")
        except ValueError:
            logger.exception("failed")
    text = caplog.text
    assert "connecting to tcp://u:***@h:1" in text
    assert "ValueError" in text and SECRET not in text


@pytest.mark.parametrize("scheduler", [f"tcp://user:{SECRET}@127.0.0.1:1", f"tls://user:{SECRET}@127.0.0.1:1",
                                       f"tcp://user:{quote(SECRET + '@:/', safe='')}@127.0.0.1:1",
                                       f"user:{SECRET}@127.0.0.1:1", f"tcp://user:{SECRET}@x@127.0.0.1:1"])
def test_cli_scheduler_with_a_password__refused_masked_everywhere(tmp_path, monkeypatch, capsys, scheduler):
    """Dask addresses take no credentials: refused before anything connects, the password in no output."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # the per-user error log, were one written
    out = tmp_path / "d.zarr"
    code, stdout, stderr = call_main(monkeypatch, capsys, "simulate", "--out", out, "--samples", 50,
                                     "--scheduler", scheduler)
    assert code == 2
    assert_one_error_line(stderr, "carries credentials")
    assert SECRET not in stdout + stderr and quote(SECRET, safe="") not in stdout + stderr
    for written in tmp_path.rglob("*"):
        assert not written.is_file() or SECRET.encode() not in written.read_bytes()


def test_check_scheduler_address__plain_addresses_pass():
    for address in ("tcp://127.0.0.1:8786", "tls://scheduler.example.org:8786", "127.0.0.1:8786", "inproc://x/1"):
        assert check_scheduler_address(address) == address
