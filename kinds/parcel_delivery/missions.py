"""The mission signed into the carrier's task, from the recorded state (a re-sent task
carries the same mission, with the same id, and the agent never repeats it)."""

from __future__ import annotations

from typing import Any

from kinds.parcel_delivery.conf import load_s
from kinds.parcel_delivery.models import CARRIER, Delivery
from kinds.parcel_delivery.planning import (
    CRUISE_ALTITUDE_M,
    DROP_ALTITUDE_M,
    LOAD_ALTITUDE_M,
)
from services.models import Assignment

#: Used when a vehicle declares no top speed.
DEFAULT_SPEED_MPS = 8.0


def vehicle_mission(*, assignment: Assignment) -> dict[str, Any] | None:
    """The carrier's ``parcel`` mission: collect the parcel where it waits, bring it
    to the drop-off, release it, go home. None for another role or no delivery."""
    delivery = Delivery.objects.filter(pk=assignment.session_id).first()
    if delivery is None or assignment.role != CARRIER:
        return None
    speed = float(assignment.vehicle.attributes.get("max_speed_mps") or DEFAULT_SPEED_MPS)
    return {
        "kind": "parcel",
        "id": f"{assignment.session_id}-{CARRIER}-{assignment.pk}",
        "pickup": list(delivery.pickup),
        "dropoff": list(delivery.dropoff),
        "altitude_m": CRUISE_ALTITUDE_M,
        "load_altitude_m": LOAD_ALTITUDE_M,
        "load_s": load_s(),
        "drop_altitude_m": DROP_ALTITUDE_M,
        "speed_mps": speed,
    }
