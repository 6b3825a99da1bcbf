"""Live vehicle status: who is online, maintenance, staleness. Writes and selectors."""

from __future__ import annotations

from collections.abc import Iterable
from datetime import datetime
from typing import Any

from django.conf import settings
from django.db import transaction
from django.db.models import QuerySet
from django.utils import timezone

from fleet.feed import fleet_notify
from fleet.liveness import Live, vehicles_fresh, vehicles_live, vehicles_seen
from fleet.models import Vehicle
from fleet.outbox import vehicle_group
from fleet.servers import vehicles_silence
from operations.layer import group_send_after_commit

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
    now = now or timezone.now()
    rows = _rows(Vehicle.objects.exclude(status__in=_NOT_ONLINE))
    if not rows:
        return []
    silent = _silent(rows, now)
    if not silent:
        return []
    with transaction.atomic():
        locked = _rows(
            Vehicle.objects.select_for_update(skip_locked=True)
            .filter(pk__in=silent)
            .exclude(status__in=_NOT_ONLINE)
        )
        stale = _silent(locked, now)
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


def _rows(vehicles: QuerySet[Vehicle]) -> dict[Any, tuple[datetime | None, Any]]:
    """id: (the row's last_seen, the process holding its uplink)."""
    return {
        pk: (seen, server)
        for pk, seen, server in vehicles.values_list("pk", "last_seen", "uplink_server")
    }


def _silent(
    rows: dict[Any, tuple[datetime | None, Any]], now: datetime
) -> dict[Any, datetime | None]:
    """Of ``rows`` (id: the row's last_seen and uplink server), those silent by their
    own doing for longer than ``IOUV_OFFLINE_AFTER_S`` at ``now`` (fleet.servers: the
    platform's own absence does not count), with when they were last heard (None:
    never)."""
    heard = vehicles_seen(rows)
    latest: dict[Any, tuple[datetime | None, Any]] = {}
    for pk, (row_seen, server) in rows.items():
        times = (at for at in (row_seen, heard.get(str(pk))) if at is not None)
        latest[pk] = (max(times, default=None), server)
    silence = vehicles_silence(((pk, seen, server) for pk, (seen, server) in latest.items()), now)
    limit = float(settings.IOUV_OFFLINE_AFTER_S)
    return {
        pk: latest[pk][0]
        for pk, silent_s in silence.items()
        if silent_s is None or silent_s > limit
    }


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
