"""Live vehicle status: who is online, maintenance, staleness. Writes and selectors."""

from __future__ import annotations

from collections.abc import Iterable
from datetime import datetime, timedelta
from typing import Any

from django.conf import settings
from django.db import transaction
from django.db.models import QuerySet
from django.utils import timezone

from fleet.feed import fleet_notify
from fleet.models import Vehicle

BUSY = (Vehicle.Status.RESERVED, Vehicle.Status.IN_SERVICE)


class FleetError(Exception):
    """A fleet change that is not allowed now; the message says why."""


def online_cutoff(now: datetime | None = None) -> datetime:
    """Vehicles last seen before this instant count as offline."""
    return (now or timezone.now()) - timedelta(seconds=settings.IOUV_OFFLINE_AFTER_S)


def vehicles_online(now: datetime | None = None) -> QuerySet[Vehicle]:
    """Vehicles whose agent has been heard from recently and that are not offline."""
    return Vehicle.objects.exclude(status=Vehicle.Status.OFFLINE).filter(
        maintenance=False, last_seen__gte=online_cutoff(now)
    )


def vehicle_set_maintenance(*, vehicle: Vehicle, on: bool) -> Vehicle:
    """Take ``vehicle`` out of service (``on``) or put it back.

    Raises FleetError when the vehicle is in a session: end the session first, so
    nobody loses control of a moving vehicle to a paperwork change.
    """
    with transaction.atomic():
        locked = Vehicle.objects.select_for_update().get(pk=vehicle.pk)
        if on and locked.status in BUSY:
            raise FleetError(
                f"{locked.name} is {locked.get_status_display()}; end its session first"
            )
        locked.maintenance = on
        if on:
            locked.status = Vehicle.Status.MAINTENANCE
        elif locked.status == Vehicle.Status.MAINTENANCE:
            seen = locked.last_seen is not None and locked.last_seen >= online_cutoff()
            locked.status = Vehicle.Status.IDLE if seen else Vehicle.Status.OFFLINE
        locked.save(update_fields=["maintenance", "status"])
        fleet_notify([locked.pk])
    return locked


def vehicles_mark_stale_offline(*, now: datetime | None = None) -> list[Any]:
    """Mark offline every vehicle whose heartbeats stopped; returns their ids."""
    with transaction.atomic():
        stale = list(
            Vehicle.objects.select_for_update(skip_locked=True)
            .filter(last_seen__lt=online_cutoff(now))
            .exclude(status__in=[Vehicle.Status.OFFLINE, Vehicle.Status.MAINTENANCE])
            .values_list("pk", flat=True)
        )
        if stale:
            Vehicle.objects.filter(pk__in=stale).update(status=Vehicle.Status.OFFLINE)
            fleet_notify(stale)
    return stale


def vehicle_summary(vehicle: Vehicle) -> dict[str, Any]:
    """What a monitor sees of one vehicle (JSON-ready)."""
    return {
        "id": str(vehicle.pk),
        "name": vehicle.name,
        "type": vehicle.vehicle_type.name,
        "kind": vehicle.vehicle_type.kind,
        "station": vehicle.station.name,
        "status": vehicle.status,
        "maintenance": vehicle.maintenance,
        "battery": vehicle.battery,
        "position": (
            {"lat": vehicle.lat, "lon": vehicle.lon, "alt": vehicle.alt}
            if vehicle.lat is not None and vehicle.lon is not None
            else None
        ),
        "last_seen": vehicle.last_seen.isoformat() if vehicle.last_seen else None,
    }


def fleet_snapshot(ids: Iterable[Any] | None = None) -> list[dict[str, Any]]:
    """Summaries of all vehicles, or of ``ids``."""
    qs = Vehicle.objects.select_related("vehicle_type", "station")
    if ids is not None:
        qs = qs.filter(pk__in=list(ids))
    return [vehicle_summary(v) for v in qs]
