"""Fixtures of the services tests: on-commit work that runs, and a live session."""

from __future__ import annotations

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
