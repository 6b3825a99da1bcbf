"""The health check answers on plain http while everything else is sent to https:
proxies' health checks reach the platform processes behind TLS over plain http."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from django.test import Client

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.django_db
def test_healthz_answers_plain_http_while_pages_redirect_to_https(settings) -> None:
    settings.SECURE_SSL_REDIRECT = True
    settings.SECURE_PROXY_SSL_HEADER = ("HTTP_X_FORWARDED_PROTO", "https")
    client = Client()
    health = client.get("/healthz")
    assert health.status_code == 200 and health.json()["ok"] is True
    login = client.get("/accounts/login/")
    assert login.status_code == 301 and login["Location"].startswith("https://")
    # Through the proxy, https: the login page itself.
    assert client.get("/accounts/login/", HTTP_X_FORWARDED_PROTO="https").status_code == 200


#: Run in a process with production settings: where SecurityMiddleware sends each path.
_REDIRECTS = """
import json
from django.middleware.security import SecurityMiddleware
from django.test import RequestFactory

middleware = SecurityMiddleware(lambda request: None)
answers = {}
for path in ("/healthz", "/accounts/login/", "/healthz/x", "/api/v1/services"):
    redirect = middleware.process_request(RequestFactory().get(path, HTTP_HOST="iouv.example.org"))
    answers[path] = redirect["Location"] if redirect else None
print(json.dumps(answers))
"""


def test_production_settings_redirect_everything_but_healthz(tmp_path) -> None:
    """The settings as a production process reads them from its environment (HTTPS
    enforced by default, behind a proxy)."""
    key_file = tmp_path / "secret"
    key_file.write_text("x" * 30 + "-a-long-random-production-secret-value-" + "y" * 20)
    signing = tmp_path / "signing.pem"
    signing.write_text("placeholder: only read when a task is signed")
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("SECURE_", "IOUV_", "DEBUG", "SECRET_KEY", "BEHIND_PROXY"))
    }
    env.update(
        DATABASE_URL="postgres://postgres@127.0.0.1:5432/test",
        REDIS_URL="redis://127.0.0.1:6379/0",
        SECRET_KEY_FILE=str(key_file),
        IOUV_SIGNING_KEY_FILE=str(signing),
        ALLOWED_HOSTS="iouv.example.org",
        BEHIND_PROXY="1",
        IOUV_VAR_DIR=str(tmp_path / "var"),
    )
    result = subprocess.run(
        [sys.executable, "manage.py", "shell", "-c", _REDIRECTS],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout.strip().splitlines()[-1]) == {
        "/healthz": None,
        "/accounts/login/": "https://iouv.example.org/accounts/login/",
        "/healthz/x": "https://iouv.example.org/healthz/x",
        "/api/v1/services": "https://iouv.example.org/api/v1/services",
    }
