"""Celery tasks of the services app: the supervisor's timers.

They keep no state of their own: each reads the database, so a worker restart loses
nothing and running one twice changes nothing. Each service kind has its own tasks
(``kinds/<kind>/tasks.py``).
"""

from __future__ import annotations

from celery import shared_task
from django.conf import settings

from iouv.celery import app
from services.supervision import (
    sessions_end_vehicle_lost,
    sessions_expire_grace,
    sessions_expire_time_limit,
    sessions_expire_unconnected,
    sessions_expire_undelivered,
)


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
