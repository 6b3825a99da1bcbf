"""Celery tasks of the fleet app (thin: they call fleet.status)."""

from __future__ import annotations

from celery import shared_task
from django.conf import settings

from fleet.status import vehicles_mark_stale_offline
from iouv.celery import app


@shared_task(name="fleet.sweep_offline")
def fleet_sweep_offline() -> int:
    """Mark offline the vehicles whose heartbeats stopped; returns how many.

    The uplink consumer notices a closed socket at once; this sweep catches agents
    whose socket stays half-open (a vehicle that drove out of coverage) and platform
    processes that died holding a socket.
    """
    return len(vehicles_mark_stale_offline())


@app.on_after_finalize.connect
def _schedule(sender, **kwargs) -> None:  # type: ignore[no-untyped-def]
    sender.add_periodic_task(
        max(1.0, settings.IOUV_OFFLINE_AFTER_S / 2),
        fleet_sweep_offline.s(),
        name="mark silent vehicles offline",
    )
