"""Passwords are masked in every URL and connection-string form libpq accepts."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mpi_lidar.learning.tune import masked
from mpi_lidar.redact import redact

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
