"""Celery tasks of parcel delivery: its steps and its timer. They keep no state of
their own, so a killed worker loses nothing and running one twice changes nothing."""

from __future__ import annotations

from typing import Any

from celery import shared_task
from django.conf import settings
from django.db import transaction

from iouv.celery import app


def delivery_schedule(session_id: Any) -> None:
    """Run a step of the delivery after the current transaction commits."""
    transaction.on_commit(lambda: delivery_step.delay(str(session_id)), robust=True)


@shared_task(name="parcel_delivery.step", acks_late=True)
def delivery_step(session_id: str) -> str | None:
    """One step of a delivery's workflow (idempotent)."""
    from kinds.parcel_delivery.workflow import delivery_advance

    return delivery_advance(session_id)


@shared_task(name="parcel_delivery.tick")
def parcel_deliveries_tick() -> int:
    """Re-run every unfinished delivery: timers, waiting, lost messages."""
    from kinds.parcel_delivery.workflow import deliveries_tick

    return deliveries_tick()


@app.on_after_finalize.connect
def _schedule(sender, **kwargs) -> None:  # type: ignore[no-untyped-def]
    sender.add_periodic_task(
        settings.IOUV_MISSION_TICK_S, parcel_deliveries_tick.s(), name="advance deliveries"
    )
