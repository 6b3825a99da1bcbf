"""What is happening in a live session now, from the facts its log holds: whether
someone controls its vehicle (:func:`controller_gone`), and in words for its pages
(:func:`session_situation`). The periodic rules (services.supervision.timers) decide
from the same facts.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from datetime import timedelta
from typing import Any

from django.conf import settings

from fleet.models import Vehicle
from services.kinds import ServiceKind, UnknownKind, kind_of
from services.models import Service, Session, SessionEvent
from services.sessions.selectors import failsafe_sentence

log = logging.getLogger(__name__)

#: The longest reason the supervisor writes into a session or a message.
REASON_MAX = 300


def service_kind(service: Service) -> ServiceKind | None:
    """The service's kind; None (logged) when it is not installed here."""
    try:
        return kind_of(service)
    except UnknownKind:
        log.warning("service %s: its kind %r is not installed", service.slug, service.kind)
        return None


#: Log events that show the session's controller back (or still there) and gone.
CONTROLLER_BACK = frozenset(
    {"user_connected", "link_recovered", "vehicle_online", "control_handover"}
)


CONTROLLER_GONE = frozenset({"unintentional_end", "user_disconnected", "control_released"})


def _absence(session: Session) -> Iterator[SessionEvent]:
    """What the session's log says of the present absence of its controller, newest
    first: the fail-safes and the controller leaving or letting go since a controller
    was last there; nothing while one is. Facts the agent reported count: a controller
    connecting, its link recovering on the socket it kept open, the vehicle coming back
    online with a controller still connected to it, against a fail-safe or the
    controller leaving. Viewers come and go without changing anything."""
    events = session.events.filter(kind__in=sorted(CONTROLLER_BACK | CONTROLLER_GONE))
    for event in events.order_by("-seq").iterator():
        data = event.data if isinstance(event.data, dict) else {}
        if event.kind in ("user_connected", "user_disconnected") and data.get("role") == "viewer":
            continue
        if event.kind == "vehicle_online" and not data.get("controller"):
            continue  # the agent is back; whether its user is, it says separately
        if event.kind in CONTROLLER_BACK:
            return
        yield event


def controller_gone(session: Session) -> SessionEvent | None:
    """The event since which nobody controls the session's vehicle (the newest word of
    its :func:`_absence`), or None while someone does (or nobody ever did: see
    :func:`sessions_expire_unconnected`)."""
    return next(_absence(session), None)


def failsafe_words(data: dict[str, Any]) -> str:
    """An ``unintentional_end``'s fail-safe in words (services.sessions.selectors)."""
    pk = data.get("vehicle")
    vehicle = Vehicle.objects.filter(pk=pk).first() if pk else None
    return failsafe_sentence(
        cause=str(data.get("cause", "unknown")),
        action=str(data.get("action", "stop")),
        vehicle=vehicle,
    )


def session_situation(session: Session) -> dict[str, Any]:
    """What is happening in a live session now, in a person's words, from its log.

    ``live`` is False while nobody controls its vehicle (a fail-safe, the user gone)
    and ``ends_at`` then says when the session ends unless the controller comes back;
    ``text`` says which, e.g. "The driver's link was lost: the vehicle performed stop
    on its own. The session ends unless the driver reconnects." A session's state
    alone ("active") would hide that.
    """
    kind = service_kind(session.service)
    if kind is not None and not kind.user_drives:
        # Nobody drives an autonomous session: the platform runs it.
        words = kind.situation(session) or "It runs by itself: nobody drives it."
        return {"live": True, "text": words, "ends_at": None}
    absence = list(_absence(session))
    if not absence:
        if session.state == Session.State.ASSIGNED:
            return {"live": True, "text": "Waiting for the driver to connect.", "ends_at": None}
        driver = session.user.get_username()
        return {"live": True, "text": f"{driver} is in control.", "ends_at": None}
    gone = absence[0]
    ends_at = gone.created_at + timedelta(seconds=settings.IOUV_RECONNECT_GRACE_S)
    # What the vehicle did on its own says more than that the driver's socket closed,
    # whichever the agent reported last (a closed tab: the link lost, with the
    # fail-safe, and the socket gone); a release of control, a choice, says more still.
    failsafe = None
    if gone.kind != "control_released":
        failsafe = next((e for e in absence if e.kind == "unintentional_end"), None)
    if failsafe is not None:
        words = failsafe_words(failsafe.data if isinstance(failsafe.data, dict) else {})
        text = f"Nobody is in control: {words}. The session ends unless the driver reconnects."
        text = text[0].upper() + text[1:]
    elif gone.kind == "control_released":
        text = "The driver released control. The session ends unless they take it back."
    else:
        text = "The driver left. The session ends unless they come back."
    return {"live": False, "text": text, "ends_at": ends_at}
