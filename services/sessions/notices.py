"""Notices: telling people outside a session what happened, once, whatever fails.

A kind decides *what* to tell and to whom (:func:`notice_create`, in the transaction
that records the moment: something found, a delivery on its way); this module makes sure
it is told exactly once per channel:

* each notice is one row per (session, channel, topic): a step that runs twice pages
  nobody twice;
* :func:`notices_send` claims a notice with a conditional UPDATE (one worker wins, on
  any database) for a lease longer than one attempt, and counts the attempt, before
  sending: a worker killed mid-send leaves a trace, and once the lease lapses the
  notice goes again with the same idempotency key (``Idempotency-Key`` for a webhook,
  ``Message-ID`` for an e-mail), so the receiver can drop the repeat;
* sending runs in a Celery task of its own (``services.tasks``), retried with growing
  delays while anything is unsent, and a periodic timer retries what is still pending.

Every notice sent is logged in its session as ``notice_sent`` (channel, topic, level,
message, and the payload's position if any): the dashboard channel is exactly that log
entry, which the monitors' page shows as an alert.
"""

from __future__ import annotations

import json
import logging
import urllib.error
import urllib.request
from datetime import timedelta
from typing import Any

from celery import shared_task
from django.conf import settings
from django.core.mail import EmailMessage
from django.db import transaction
from django.db.models import F, Q
from django.utils import timezone

from services.models import Notice, Session
from services.sessions.log import event_append

log = logging.getLogger(__name__)

#: A notice not sent after this many attempts is left for a person to look at.
ATTEMPTS_MAX = 8


def notice_create(
    *,
    session: Session,
    channel: str,
    topic: str,
    message: str,
    target: str = "",
    subject: str = "",
    payload: dict[str, Any] | None = None,
    level: str = Notice.Level.INFO,
) -> Notice:
    """Owe ``message`` on ``channel`` about ``topic`` of ``session``; an existing one
    is left alone (returned as it is). Sent after the current transaction commits."""
    notice, created = Notice.objects.get_or_create(
        session=session,
        channel=channel,
        topic=topic,
        defaults={
            "target": target,
            "subject": subject[:200],
            "message": message,
            "payload": payload or {},
            "level": level,
        },
    )
    if created:
        notices_schedule(session.pk)
    return notice


def notices_pending(session_id: Any = None) -> list[Any]:
    """The sessions with notices still to send (or whether ``session_id`` has)."""
    pending = Notice.objects.filter(sent_at__isnull=True, attempts__lt=ATTEMPTS_MAX)
    if session_id is not None:
        pending = pending.filter(session_id=session_id)
    return sorted(set(pending.values_list("session_id", flat=True)))


def notices_schedule(session_id: Any) -> None:
    """Send the session's pending notices from their own task once the current
    transaction commits."""
    transaction.on_commit(lambda: services_notices_send.delay(str(session_id)), robust=True)


class NoticeNotSent(Exception):
    """A notice could not be delivered this time; its task retries later."""


def notices_send(session_id: Any) -> int:
    """Send the session's pending notices; returns how many were sent now."""
    sent = 0
    pending = Notice.objects.filter(
        session_id=session_id, sent_at__isnull=True, attempts__lt=ATTEMPTS_MAX
    ).values_list("pk", flat=True)
    lease = timedelta(seconds=2 * settings.IOUV_WEBHOOK_TIMEOUT_S + 5)
    for pk in list(pending):
        now = timezone.now()
        claimed = (
            Notice.objects.filter(pk=pk, sent_at__isnull=True)
            .filter(Q(claimed_until__isnull=True) | Q(claimed_until__lt=now))
            .update(claimed_until=now + lease, attempts=F("attempts") + 1)
        )
        if not claimed:
            continue  # sent, or another worker is sending it right now
        notice = Notice.objects.select_related("session").get(pk=pk)
        try:
            _deliver(notice)
        except Exception as exc:
            log.warning("notice %s (%s, %s) failed: %s", pk, notice.topic, notice.channel, exc)
            Notice.objects.filter(pk=pk).update(last_error=str(exc)[:300], claimed_until=None)
            continue
        with transaction.atomic():
            Notice.objects.filter(pk=pk).update(
                sent_at=timezone.now(), last_error="", claimed_until=None
            )
            event_append(
                session=notice.session,
                kind="notice_sent",
                data={
                    "channel": notice.channel,
                    "topic": notice.topic,
                    "level": notice.level,
                    "target": notice.target,
                    "message": notice.message,
                    "lat": notice.payload.get("lat"),
                    "lon": notice.payload.get("lon"),
                },
            )
        sent += 1
    return sent


def notices_send_or_retry(session_id: Any) -> int:
    """:func:`notices_send`, raising NoticeNotSent when something is still unsent (so
    the task calling it retries later)."""
    sent = notices_send(session_id)
    if notices_pending(session_id):
        raise NoticeNotSent(f"session {session_id}: notices still unsent after this attempt")
    return sent


def idempotency_key(notice: Notice) -> str:
    """Stable across attempts: the receiver drops a repeat by it."""
    return f"iouv-{notice.topic}-{notice.session_id}-{notice.channel}"


def _deliver(notice: Notice) -> None:
    if notice.channel == Notice.Channel.DASHBOARD:
        return  # the notice_sent log entry is what the monitors' dashboard shows
    if notice.channel == Notice.Channel.EMAIL:
        message = EmailMessage(
            subject=notice.subject or f"[IoUV] {notice.topic.replace('_', ' ')}",
            body=notice.message,
            to=[notice.target],
            headers={"Message-ID": f"<{idempotency_key(notice)}@iouv>"},
        )
        message.send(fail_silently=False)
        return
    request = urllib.request.Request(
        notice.target,
        data=json.dumps(
            {"topic": notice.topic, "message": notice.message, **notice.payload}
        ).encode(),
        headers={
            "Content-Type": "application/json",
            "Idempotency-Key": idempotency_key(notice),
            "User-Agent": "IoUV/1",
        },
        method="POST",
    )
    try:
        with urllib.request.urlopen(request, timeout=settings.IOUV_WEBHOOK_TIMEOUT_S) as response:
            if not 200 <= response.status < 300:
                raise RuntimeError(f"webhook answered {response.status}")
    except urllib.error.HTTPError as exc:
        raise RuntimeError(f"webhook answered {exc.code}") from None


@shared_task(
    name="services.notices_send",
    acks_late=True,
    autoretry_for=(NoticeNotSent,),
    max_retries=8,
    retry_backoff=2,
    retry_backoff_max=120,
    retry_jitter=True,
)
def services_notices_send(session_id: str) -> int:
    """Send a session's pending notices; retried with growing delays while any is
    still unsent (a webhook down, a mail server away)."""
    return notices_send_or_retry(session_id)
