"""Pushes session changes to browsers (the session's page and the monitors)."""

from __future__ import annotations

from typing import Any

from asgiref.sync import async_to_sync
from channels.layers import get_channel_layer
from django.db import transaction

SESSIONS_GROUP = "sessions"  # monitors: every session


def session_group(session_id: Any) -> str:
    return f"session-{str(session_id).replace('-', '')}"


def session_notify(*, session_id: Any, event: dict[str, Any]) -> None:
    """After commit, send one logged event to the session's page and to monitors."""
    message = {"type": "session.event", "session_id": str(session_id), "event": event}

    def send() -> None:
        layer = get_channel_layer()
        if layer is None:
            return
        async_to_sync(layer.group_send)(session_group(session_id), message)
        async_to_sync(layer.group_send)(SESSIONS_GROUP, message)

    transaction.on_commit(send)
