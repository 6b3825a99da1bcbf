"""Pushes session changes to browsers (the session's page and the monitors)."""

from __future__ import annotations

from typing import Any

from operations.layer import group_send_after_commit

SESSIONS_GROUP = "sessions"  # monitors: every session


def session_group(session_id: Any) -> str:
    return f"session-{str(session_id).replace('-', '')}"


def session_notify(*, session_id: Any, event: dict[str, Any]) -> None:
    """After commit, send one logged event to the session's page and to monitors."""
    message = {"type": "session.event", "session_id": str(session_id), "event": event}

    group_send_after_commit(session_group(session_id), message)
    group_send_after_commit(SESSIONS_GROUP, message)


def session_notify_many(
    *, session_id: Any, events: list[dict[str, Any]], new: bool = False
) -> None:
    """After commit, send several logged events of one session, in order, in one
    message per group (consumers show them one by one, as if sent singly).

    ``new``: the session was created in the committing transaction, so no page can
    follow it yet; only the monitors are told.
    """
    if not events:
        return
    message = {"type": "session.events", "session_id": str(session_id), "events": events}
    if not new:
        group_send_after_commit(session_group(session_id), message)
    group_send_after_commit(SESSIONS_GROUP, message)
