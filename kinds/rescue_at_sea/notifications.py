"""Telling the rescue team, and the monitors, what the mission found.

What to say and to whom is decided here, with the state that calls for it; the core's
notices (services.sessions.notices) deliver it: once per channel, retried until it goes through,
with a stable idempotency key.
"""

from __future__ import annotations

from typing import Any

from kinds.rescue_at_sea.models import SEARCH, Mission, RescueTeam
from services.kit import notice_create
from services.models import Assignment, Notice

#: The notice's topic: one per mission and channel.
PERSON_IN_WATER = "person_in_water"


def _team(mission: Mission) -> tuple[str | None, RescueTeam | None]:
    """The station whose rescue team is told (the first search vehicle's), and its
    team if it has one."""
    first = (
        Assignment.objects.filter(session_id=mission.pk, role=SEARCH)
        .select_related("vehicle__station")
        .order_by("created_at")
        .first()
    )
    if first is None:
        return None, None
    station = first.vehicle.station
    return station.name, RescueTeam.objects.filter(station=station).first()


def notices_create(mission: Mission) -> None:
    """The person is found: owe the monitors' dashboard and the rescue team (by
    e-mail and webhook, where its station has them) the position."""
    detection = mission.detection or {}
    station, team = _team(mission)
    lat, lon = detection.get("lat"), detection.get("lon")
    confidence = detection.get("confidence")
    text = (
        f"Person in the water at {lat:.5f}, {lon:.5f}"
        + (f" (detection confidence {confidence:.2f})" if confidence is not None else "")
        + f", found by {detection.get('vehicle_name', 'a search drone')}. "
        "A life jacket is on its way."
    )
    payload: dict[str, Any] = {
        "event": PERSON_IN_WATER,
        "mission": str(mission.pk),
        "lat": lat,
        "lon": lon,
        "confidence": confidence,
        "detected_at": mission.detected_at.isoformat() if mission.detected_at else None,
        "station": station,
        "team": team.name if team else None,
    }
    channels = [(Notice.Channel.DASHBOARD, "")]
    if team is not None and team.email:
        channels.append((Notice.Channel.EMAIL, team.email))
    if team is not None and team.webhook:
        channels.append((Notice.Channel.WEBHOOK, team.webhook))
    for channel, target in channels:
        notice_create(
            session=mission.session,
            channel=channel,
            topic=PERSON_IN_WATER,
            target=target,
            level=Notice.Level.BAD,
            subject=f"[IoUV rescue] Person in the water at {lat:.5f}, {lon:.5f}",
            message=f"{text}\n\nPosition: {lat:.6f}, {lon:.6f}\nMission: {mission.pk}\n"
            if channel == Notice.Channel.EMAIL
            else text,
            payload=payload,
        )


def mission_alert(mission: Mission, *, topic: str, text: str) -> None:
    """A warning for the monitors' dashboard (the mission waits, timed out...), once
    per topic."""
    notice_create(
        session=mission.session,
        channel=Notice.Channel.DASHBOARD,
        topic=topic,
        level=Notice.Level.WARN,
        message=f"{mission.session.service.name}: {text}",
    )
