"""Celery tasks of the services app: the supervisor's timers and the notices.

They keep no state of their own: each reads the database, so a worker restart loses
nothing and running one twice changes nothing. Each service kind has its own tasks
(``kinds/<kind>/tasks.py``).
"""

from __future__ import annotations

import logging

from celery import shared_task
from django.conf import settings

from iouv.celery import app
from services.records.keeping import records_expire

# The notices' own sending task lives with them (services.sessions.notices), which
# schedules it; it is named here too so that this module lists every task of the app.
from services.sessions.notices import notices_pending, notices_send, services_notices_send

# Likewise the task that closes an ended session's SFU room and converts and chains its
# recording lives with the session's video (services.sessions.video).
from services.sessions.video import services_sfu_session_ended
from services.sfu import (
    services_sfu_room_open,
    services_sfu_rooms_ensure,
    sfu_configured,
)
from services.supervision.timers import (
    sessions_end_vehicle_lost,
    sessions_expire_grace,
    sessions_expire_time_limit,
    sessions_expire_unconnected,
    sessions_expire_undelivered,
)

log = logging.getLogger(__name__)


@shared_task(name="services.records_expire")
def services_records_expire() -> int:
    """Delete the flight records older than the retention setting."""
    return records_expire()


@shared_task(name="services.expire_grace")
def services_expire_grace() -> int:
    """End sessions whose user did not come back after a fail-safe."""
    return len(sessions_expire_grace())


@shared_task(name="services.expire_unconnected")
def services_expire_unconnected() -> int:
    """End sessions nobody connected to in time."""
    return len(sessions_expire_unconnected())


@shared_task(name="services.end_vehicle_lost")
def services_end_vehicle_lost() -> int:
    """End sessions whose vehicle has been offline too long."""
    return len(sessions_end_vehicle_lost())


@shared_task(name="services.expire_time_limit")
def services_expire_time_limit() -> int:
    """Revoke sessions past their service's time limit."""
    return len(sessions_expire_time_limit())


@shared_task(name="services.expire_undelivered")
def services_expire_undelivered() -> int:
    """Fail sessions whose vehicle task was never accepted."""
    return len(sessions_expire_undelivered())


@shared_task(name="services.notices_retry")
def services_notices_retry() -> int:
    """Try again every notice still unsent (its task's retries ran out, or its message
    was lost with a worker)."""
    pending = notices_pending()
    for session_id in pending:
        try:
            notices_send(session_id)
        except Exception:  # one broken notice must not stop the others
            log.exception("notices of session %s: sending failed", session_id)
    return len(pending)


@app.on_after_finalize.connect
def _schedule(sender, **kwargs) -> None:  # type: ignore[no-untyped-def]
    tick = settings.IOUV_SUPERVISION_TICK_S
    sender.add_periodic_task(tick, services_expire_grace.s(), name="end abandoned sessions")
    sender.add_periodic_task(tick, services_end_vehicle_lost.s(), name="end lost vehicles")
    sender.add_periodic_task(tick, services_expire_time_limit.s(), name="enforce time limits")
    sender.add_periodic_task(
        15.0, services_expire_unconnected.s(), name="end sessions nobody joined"
    )
    sender.add_periodic_task(15.0, services_expire_undelivered.s(), name="fail undelivered tasks")
    sender.add_periodic_task(10.0, services_notices_retry.s(), name="retry unsent notices")
    sender.add_periodic_task(3600.0, services_records_expire.s(), name="expire flight records")
    if sfu_configured():
        sender.add_periodic_task(
            settings.IOUV_JANUS_ROOMS_CHECK_S,
            services_sfu_rooms_ensure.s(),
            name="make again the SFU rooms Janus lost",
        )


__all__ = [
    "services_end_vehicle_lost",
    "services_expire_grace",
    "services_expire_time_limit",
    "services_expire_unconnected",
    "services_expire_undelivered",
    "services_notices_retry",
    "services_notices_send",
    "services_records_expire",
    "services_sfu_room_open",
    "services_sfu_rooms_ensure",
    "services_sfu_session_ended",
]
