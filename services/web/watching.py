"""What a session's pages show, and who may watch them: shared by the portal's session
page and the pages kinds add (through services.kit).
"""

from __future__ import annotations

from typing import Any

from django.http import Http404
from django.shortcuts import get_object_or_404

from accounts.users import AuthenticatedHttpRequest
from services.models import Session
from services.sessions.words import event_text


def log_lines(session: Session) -> list[dict[str, Any]]:
    """The latest log events, oldest first (the session's story, in order), as the
    session pages list them; the page adds newer ones at the end."""
    return [
        {"at": event.created_at, "label": event_text(event.kind, event.data), "detail": ""}
        for event in list(session.events.order_by("-seq")[:30])[::-1]
    ]


def session_vehicle_names(session: Session) -> list[str]:
    """Every vehicle the session had, in the order it had them: a session page names
    them after the end too."""
    names = session.assignments.order_by("created_at").values_list("vehicle__name", flat=True)
    return list(dict.fromkeys(names))


def session_watched(request: AuthenticatedHttpRequest, session_id: str) -> Session:
    """The session if the request's user may watch it (its own user, or a monitor);
    404 otherwise, so others' sessions are not even confirmed to exist."""
    session = get_object_or_404(Session.objects.select_related("service"), pk=session_id)
    if session.user_id != request.user.pk and not request.user.has_perm("fleet.view_fleet"):
        raise Http404("no such session")
    return session
