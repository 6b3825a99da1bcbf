"""Fixtures of the services tests: on-commit work that runs, a live session, an SFU
configured (its recordings in a folder of the test's own)."""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Any

import pytest
from django.test import Client

from services.models import Session
from tests.deployment import alices_session


@pytest.fixture
def committing(django_capture_on_commit_callbacks: Any) -> Any:
    """A block whose on-commit work (the pushes to agents) runs, as after a real commit:
    the test itself runs inside a transaction that never commits."""
    return lambda: django_capture_on_commit_callbacks(execute=True)


@pytest.fixture
def live_session(client: Client) -> tuple[Session, str]:
    """alice's live session (see tests.deployment.alices_session), alice logged in on
    ``client``; and its vehicle's id."""
    session, vehicle = alices_session()
    client.force_login(session.user)
    return session, str(vehicle.pk)


@pytest.fixture
def rate_counters(settings: Any) -> str:
    """Rate-limit counters of this test's own (a cache key prefix no other test or
    earlier run uses): the counters live in Redis, which outlives the test database,
    whose user ids start again at 1 on every run."""
    prefix = f"test-{uuid.uuid4().hex}"
    settings.CACHES = {
        **settings.CACHES,
        "default": {**settings.CACHES["default"], "KEY_PREFIX": prefix},
    }
    return prefix


@pytest.fixture
def janus_settings(settings: Any, tmp_path: Path) -> Any:
    """The platform set up with an SFU (nothing listens at its address) that records
    into ``tmp_path``/recordings."""
    settings.IOUV_JANUS_URL = "http://127.0.0.1:9/janus"
    settings.IOUV_JANUS_PUBLIC_URL = "wss://platform.example/janus-ws/"
    settings.IOUV_JANUS_TOKEN_SECRET = "token-secret"
    settings.IOUV_JANUS_ADMIN_KEY = "admin-key"
    settings.IOUV_JANUS_REC_DIR = str(tmp_path / "recordings")
    return settings
