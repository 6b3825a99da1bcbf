"""Live vehicle status: who is online, maintenance, staleness. Writes and selectors."""

from __future__ import annotations

from collections.abc import Iterable
from datetime import datetime
from typing import Any

from django.db import transaction
from django.db.models import QuerySet

from fleet.feed import fleet_notify
from fleet.liveness import Live, online_cutoff, vehicles_fresh, vehicles_live, vehicles_seen
from fleet.models import Vehicle
from fleet.outbox import vehicle_group
from iouv.layer import group_send_after_commit

BUSY = (Vehicle.Status.RESERVED, Vehicle.Status.IN_SERVICE)


class FleetError(Exception):
    """A fleet change that is not allowed now; the message says why."""


def vehicles_online(now: datetime | None = None) -> QuerySet[Vehicle]:
    """Vehicles the platform counts online: not offline, not in maintenance.

    The status says it, not the last heartbeat: an uplink that closes marks its
    vehicle offline at once, and the sweep (:func:`vehicles_mark_stale_offline`)
    marks those that went silent. Between a silence and the next sweep a vehicle may
    still be counted here; whoever is about to rely on one vehicle checks it with
    :func:`fleet.liveness.vehicles_fresh` (``now``: kept for those callers).
    """
    del now
    return Vehicle.objects.exclude(status=Vehicle.Status.OFFLINE).filter(maintenance=False)


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
            heard = bool(vehicles_fresh([locked.pk]))
            locked.status = Vehicle.Status.IDLE if heard else Vehicle.Status.OFFLINE
        locked.save(update_fields=["maintenance", "status"])
        fleet_notify([locked.pk])
    return locked


_NOT_ONLINE = (Vehicle.Status.OFFLINE, Vehicle.Status.MAINTENANCE)


def vehicles_mark_stale_offline(*, now: datetime | None = None) -> list[Any]:
    """Mark offline every vehicle whose heartbeats stopped; returns their ids.

    Silence is read from fleet.liveness (the later of its time and the row's, since
    a hello or a profile writes the row). The rows found silent are locked and read
    again, so a vehicle heard from meanwhile stays online; each gets the time it was
    last heard as its ``last_seen`` (workflows measure how long it has been gone),
    and its uplink, if one still lives somewhere, is told so that its next heartbeat
    reaches the row again.
    """
    cutoff = online_cutoff(now)
    rows = dict(Vehicle.objects.exclude(status__in=_NOT_ONLINE).values_list("pk", "last_seen"))
    if not rows:
        return []
    silent = _silent(rows, cutoff)
    if not silent:
        return []
    with transaction.atomic():
        locked = dict(
            Vehicle.objects.select_for_update(skip_locked=True)
            .filter(pk__in=silent)
            .exclude(status__in=_NOT_ONLINE)
            .values_list("pk", "last_seen")
        )
        stale = _silent(locked, cutoff)
        for pk, heard in stale.items():
            Vehicle.objects.filter(pk=pk).update(status=Vehicle.Status.OFFLINE, last_seen=heard)
            group_send_after_commit(
                vehicle_group(pk),
                {
                    "type": "uplink.marked_offline",
                    "last_seen": heard.isoformat() if heard is not None else None,
                },
            )
        fleet_notify(stale)
    return list(stale)


def _silent(rows: dict[Any, datetime | None], cutoff: datetime) -> dict[Any, datetime | None]:
    """Of ``rows`` (id: the row's last_seen), those last heard before ``cutoff``, with
    when they were last heard (None: never)."""
    heard = vehicles_seen(rows)
    silent: dict[Any, datetime | None] = {}
    for pk, row_seen in rows.items():
        latest = max((at for at in (row_seen, heard.get(str(pk))) if at is not None), default=None)
        if latest is None or latest < cutoff:
            silent[pk] = latest
    return silent


def vehicle_summary(vehicle: Vehicle, live: Live | None = None) -> dict[str, Any]:
    """What a monitor sees of one vehicle (JSON-ready); ``live``: what its agent last
    reported (fleet.liveness), newer than the row's battery, position and last_seen."""
    if live is not None and (vehicle.last_seen is None or live.seen_at >= vehicle.last_seen):
        return {
            **vehicle_summary(vehicle),
            **live_summary(live),
        }
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


def live_summary(live: Live) -> dict[str, Any]:
    """The fields of a vehicle's summary that its agent's reports keep changing."""
    return {
        "battery": live.battery,
        "position": (
            {"lat": live.lat, "lon": live.lon, "alt": live.alt}
            if live.lat is not None and live.lon is not None
            else None
        ),
        "last_seen": live.seen_at.isoformat(),
    }


def fleet_snapshot(ids: Iterable[Any] | None = None) -> list[dict[str, Any]]:
    """Summaries of all vehicles, or of ``ids``, with what each last reported."""
    qs = Vehicle.objects.select_related("vehicle_type", "station")
    if ids is not None:
        qs = qs.filter(pk__in=list(ids))
    vehicles = list(qs)
    live = vehicles_live(v.pk for v in vehicles)
    return [vehicle_summary(v, live.get(str(v.pk))) for v in vehicles]
