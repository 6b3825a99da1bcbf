"""Telling the rescue team: one notice per channel, sent until it succeeds, once.

A step that finds the person creates the notices (:func:`notices_create`) with the
state that calls for them; :func:`notifications_send` delivers them, from a Celery task
of their own that retries with growing delays (``tasks.rescue_notify``), and the
periodic timer retries what is still pending. Each notice is claimed with a lease before
it is sent, so two workers never send it both; a stable ``Idempotency-Key`` (webhook)
or ``Message-ID`` (e-mail) lets the receiver drop a repeat after a worker crash.
"""

from __future__ import annotations

import json
import logging
import urllib.error
import urllib.request
from datetime import timedelta
from typing import Any

from django.conf import settings
from django.core.mail import EmailMessage
from django.db import transaction
from django.db.models import F, Q
from django.utils import timezone

from fleet.models import Station
from kinds.rescue_at_sea.models import SEARCH, Mission, MissionNotification
from services.eventlog import event_append
from services.models import Assignment

log = logging.getLogger(__name__)

NOTIFY_ATTEMPTS_MAX = 8


def _team_station(mission: Mission) -> Station | None:
    first = (
        Assignment.objects.filter(session_id=mission.pk, role=SEARCH)
        .select_related("vehicle__station")
        .order_by("created_at")
        .first()
    )
    return first.vehicle.station if first else None


def notices_create(mission: Mission) -> None:
    """One notice per channel, created with the state that calls for it; existing
    ones are left alone (a step that runs twice pages nobody twice)."""
    detection = mission.detection or {}
    station = _team_station(mission)
    lat, lon = detection.get("lat"), detection.get("lon")
    confidence = detection.get("confidence")
    text = (
        f"Person in the water at {lat:.5f}, {lon:.5f}"
        + (f" (detection confidence {confidence:.2f})" if confidence is not None else "")
        + f", found by {detection.get('vehicle_name', 'a search drone')}. "
        "A life jacket is on its way."
    )
    payload = {
        "event": "person_in_water",
        "mission": str(mission.pk),
        "lat": lat,
        "lon": lon,
        "confidence": confidence,
        "detected_at": mission.detected_at.isoformat() if mission.detected_at else None,
        "station": station.name if station else None,
        "team": station.rescue_team_name if station else None,
        "message": text,
    }
    channels = [(MissionNotification.Channel.DASHBOARD, "monitors")]
    if station is not None and station.rescue_team_email:
        channels.append((MissionNotification.Channel.EMAIL, station.rescue_team_email))
    if station is not None and station.rescue_team_webhook:
        channels.append((MissionNotification.Channel.WEBHOOK, station.rescue_team_webhook))
    for channel, target in channels:
        MissionNotification.objects.get_or_create(
            mission=mission, channel=channel, defaults={"target": target, "payload": payload}
        )


def notices_pending(session_id: Any = None) -> list[Any]:
    """The missions (or whether ``session_id``'s) with notices still to send."""
    pending = MissionNotification.objects.filter(
        sent_at__isnull=True, attempts__lt=NOTIFY_ATTEMPTS_MAX
    )
    if session_id is not None:
        pending = pending.filter(mission_id=session_id)
    return sorted(set(pending.values_list("mission_id", flat=True)))


def notify_schedule(session_id: Any) -> None:
    """Send the mission's pending notices from their own task, once the current
    transaction (which created them) commits."""
    from kinds.rescue_at_sea.tasks import rescue_notify  # the task module imports this one

    transaction.on_commit(lambda: rescue_notify.delay(str(session_id)), robust=True)


class NoticeNotSent(Exception):
    """A notice could not be delivered this time (its task retries later)."""


def notifications_send(session_id: Any) -> int:
    """Send the mission's pending notices; returns how many were sent now.

    Each notice is claimed first with a conditional UPDATE (only one worker can win it,
    on any database) for a lease longer than one delivery attempt; the claim and the
    attempt count are committed before sending, so a worker killed while sending
    leaves a trace and, once the lease lapses, the notice is sent again with the same
    idempotency key. A failed attempt releases the claim for the timer's retry.
    """
    sent = 0
    pending = MissionNotification.objects.filter(
        mission_id=session_id, sent_at__isnull=True, attempts__lt=NOTIFY_ATTEMPTS_MAX
    ).values_list("pk", flat=True)
    lease = timedelta(seconds=2 * settings.IOUV_WEBHOOK_TIMEOUT_S + 5)
    for pk in list(pending):
        now = timezone.now()
        claimed = (
            MissionNotification.objects.filter(pk=pk, sent_at__isnull=True)
            .filter(Q(claimed_until__isnull=True) | Q(claimed_until__lt=now))
            .update(claimed_until=now + lease, attempts=F("attempts") + 1)
        )
        if not claimed:
            continue  # sent, or another worker is sending it right now
        notice = MissionNotification.objects.select_related("mission__session").get(pk=pk)
        try:
            _deliver(notice)
        except Exception as exc:
            log.warning("rescue notice %s (%s) failed: %s", notice.pk, notice.channel, exc)
            MissionNotification.objects.filter(pk=pk).update(
                last_error=str(exc)[:300], claimed_until=None
            )
            continue
        with transaction.atomic():
            MissionNotification.objects.filter(pk=pk).update(
                sent_at=timezone.now(), last_error="", claimed_until=None
            )
            event_append(
                session=notice.mission.session,
                kind="rescue_team_notified",
                data={
                    "channel": notice.channel,
                    "target": notice.target,
                    "message": notice.payload.get("message", ""),
                    "lat": notice.payload.get("lat"),
                    "lon": notice.payload.get("lon"),
                },
            )
        sent += 1
    return sent


def _idempotency_key(notice: MissionNotification) -> str:
    return f"iouv-rescue-{notice.mission_id}-{notice.channel}"


def _deliver(notice: MissionNotification) -> None:
    payload = notice.payload
    if notice.channel == MissionNotification.Channel.DASHBOARD:
        return  # the rescue_team_notified log entry reaches the monitors' dashboard
    if notice.channel == MissionNotification.Channel.EMAIL:
        message = EmailMessage(
            subject=f"[IoUV rescue] Person in the water at {payload['lat']:.5f}, "
            f"{payload['lon']:.5f}",
            body=payload["message"] + f"\n\nPosition: {payload['lat']:.6f}, {payload['lon']:.6f}\n"
            f"Mission: {payload['mission']}\n",
            to=[notice.target],
            headers={"Message-ID": f"<{_idempotency_key(notice)}@iouv>"},
        )
        message.send(fail_silently=False)
        return
    request = urllib.request.Request(
        notice.target,
        data=json.dumps(payload).encode(),
        headers={
            "Content-Type": "application/json",
            "Idempotency-Key": _idempotency_key(notice),
            "User-Agent": "IoUV-rescue/1",
        },
        method="POST",
    )
    try:
        with urllib.request.urlopen(request, timeout=settings.IOUV_WEBHOOK_TIMEOUT_S) as response:
            if not 200 <= response.status < 300:
                raise RuntimeError(f"webhook answered {response.status}")
    except urllib.error.HTTPError as exc:
        raise RuntimeError(f"webhook answered {exc.code}") from None
