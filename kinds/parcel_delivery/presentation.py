"""What the delivery's pages show: the map's state, the phase and the ETA."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

from django.utils import timezone

from agents.geo import distance_m
from kinds.parcel_delivery.conf import load_s
from kinds.parcel_delivery.missions import DEFAULT_SPEED_MPS
from kinds.parcel_delivery.models import CARRIER, FINAL_DELIVERY, Delivery
from services.kit import session_consequence
from services.models import Assignment

#: The log entries the timeline shows.
SHOWN = (
    "requested",
    "delivery_planned",
    "assigned",
    "delivery_state",
    "native_mission_refused",
    "native_mission_started",
    "parcel_loaded",
    "payload_released",
    "notice_sent",
    "vehicle_released",
    "state",
)


def _eta_s(delivery: Delivery, carrier: dict[str, Any] | None) -> float | None:
    """Seconds until the parcel is at the drop-off, from where the carrier is now at
    its top speed (plus the wait to load it); None when no carrier is moving it."""
    if carrier is None or carrier["lat"] is None or delivery.state in FINAL_DELIVERY:
        return None
    here = (carrier["lat"], carrier["lon"])
    speed = carrier["speed_mps"] or DEFAULT_SPEED_MPS
    if delivery.loaded_at is not None:
        return distance_m(here, delivery.dropoff) / speed
    return (distance_m(here, delivery.pickup) + distance_m(delivery.pickup, delivery.dropoff)) / (
        speed
    ) + load_s()


def delivery_json(delivery: Delivery, *, public: bool = False) -> dict[str, Any]:
    """The delivery as its live map shows it. ``public`` (the recipient's page):
    without the session's log and who asked."""
    session = delivery.session
    vehicles = []
    carrier = None
    assignments = list(
        Assignment.objects.filter(session_id=delivery.pk).select_related("vehicle__station")
    )
    for a in assignments:
        v = a.vehicle
        entry = {
            "id": str(v.pk),
            "name": v.name,
            "kind": v.vehicle_type.kind,
            "role": a.role,
            "active": a.active,
            "status": v.status,
            "lat": v.lat,
            "lon": v.lon,
            "battery": v.battery,
            "speed_mps": v.attributes.get("max_speed_mps"),
            "station": {"name": v.station.name, "lat": v.station.lat, "lon": v.station.lon},
        }
        vehicles.append(entry)
        if a.active and a.role == CARRIER:
            carrier = entry
    eta = _eta_s(delivery, carrier)
    eta_at = timezone.now() + timedelta(seconds=eta) if eta is not None else None
    out: dict[str, Any] = {
        "session": {"id": str(session.pk), "state": session.state, "reason": session.reason},
        "state": delivery.state,
        "state_label": Delivery.State(delivery.state).label,
        "final": delivery.state in FINAL_DELIVERY,
        "status": delivery.status_text,
        "pickup": list(delivery.pickup_lat_lon()),
        "waiting_at": list(delivery.pickup) if delivery.handover_lat is not None else None,
        "dropoff": list(delivery.dropoff),
        "weight_kg": delivery.weight_kg,
        "loaded": delivery.loaded_at is not None,
        "delivered": delivery.released_at is not None,
        "eta_s": round(eta) if eta is not None else None,
        "eta_at": eta_at.isoformat() if eta_at is not None else None,
        "vehicles": vehicles,
    }
    if not public:
        # What cancelling now makes the carrier do, for the user's confirmation.
        active = [a.vehicle for a in assignments if a.active]
        out["consequence"] = session_consequence(session, active)
        out["timeline"] = [
            {"seq": e.seq, "at": e.created_at.isoformat(), "kind": e.kind, "data": e.data}
            for e in session.events.filter(kind__in=SHOWN).order_by("seq")
        ]
    return out
