"""Settings modes: production passes Django's deploy checklist; secrets are required."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from iouv.env import database_from_url

ROOT = Path(__file__).resolve().parents[2]


def _manage(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    clean = {k: v for k, v in os.environ.items() if k not in _IOUV_VARS}
    return subprocess.run(
        [sys.executable, "manage.py", *args],
        cwd=ROOT,
        env={**clean, **env},
        capture_output=True,
        text=True,
        timeout=120,
    )


_IOUV_VARS = {
    "DATABASE_URL",
    "REDIS_URL",
    "SECRET_KEY",
    "DEBUG",
    "IOUV_DEV_SECRETS",
    "SECURE_SSL_REDIRECT",
    "SECURE_COOKIES",
    "IOUV_SIGNING_KEY",
    "ALLOWED_HOSTS",
}


def test_production_settings_pass_check_deploy(tmp_path):
    key_file = tmp_path / "secret"
    key_file.write_text("x" * 30 + "-a-long-random-production-secret-value-" + "y" * 20)
    signing = tmp_path / "signing.pem"
    signing.write_text("placeholder: only read when a task is signed")
    result = _manage(
        "check",
        "--deploy",
        "--fail-level",
        "WARNING",
        env={
            "DATABASE_URL": "postgres://postgres@127.0.0.1:5432/test",
            "REDIS_URL": "redis://127.0.0.1:6379/0",
            "SECRET_KEY_FILE": str(key_file),
            "IOUV_SIGNING_KEY_FILE": str(signing),
            "ALLOWED_HOSTS": "iouv.example.org",
            "IOUV_VAR_DIR": str(tmp_path / "var"),
            # Mail that leaves the machine (Django 6.1's checklist refuses the console
            # and file backends, which send nothing).
            "EMAIL_BACKEND": "django.core.mail.backends.smtp.EmailBackend",
            "EMAIL_HOST": "mail.example.org",
        },
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "no issues" in result.stdout


def test_production_refuses_to_start_without_a_secret_key(tmp_path):
    result = _manage(
        "check",
        env={
            "DATABASE_URL": "postgres://postgres@127.0.0.1:5432/test",
            "IOUV_VAR_DIR": str(tmp_path / "var"),
        },
    )
    assert result.returncode != 0
    assert "SECRET_KEY" in result.stderr


def test_embedded_mode_needs_nothing(tmp_path):
    result = _manage("check", env={"IOUV_VAR_DIR": str(tmp_path / "var")})
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "var" / "secret_key").exists()


@pytest.mark.parametrize(
    ("url", "expected"),
    [
        (
            "postgres://bob:p%40ss@db.local:6543/iouv?sslmode=require",
            {
                "HOST": "db.local",
                "PORT": "6543",
                "NAME": "iouv",
                "USER": "bob",
                "PASSWORD": "p@ss",
                "OPTIONS": {"sslmode": "require"},
            },
        ),
        ("sqlite:////tmp/x.sqlite3", {"NAME": "/tmp/x.sqlite3"}),
    ],
)
def test_database_url_parsing(url, expected):
    parsed = database_from_url(url)
    for key, value in expected.items():
        assert parsed[key] == value
