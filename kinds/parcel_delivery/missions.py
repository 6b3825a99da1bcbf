"""The mission signed into the carrier's task, from the recorded state (a re-sent task
carries the same mission, with the same id, and the agent never repeats it)."""

from __future__ import annotations

from agents.missions.parcel.spec import ParcelSpec
from agents.missions.spec import MissionSpec
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


#: The missions this kind deploys (:attr:`services.kinds.ServiceKind.missions`).
MISSIONS: tuple[type[MissionSpec], ...] = (ParcelSpec,)


def vehicle_mission(*, assignment: Assignment) -> ParcelSpec | None:
    """The carrier's ``parcel`` mission (agents/missions/parcel/): collect the parcel
    where it waits, bring it to the drop-off, release it, go home. None for another
    role or no delivery. Raises MissionError if the recorded state makes no valid one."""
    delivery = Delivery.objects.filter(pk=assignment.session_id).first()
    if delivery is None or assignment.role != CARRIER:
        return None
    speed = float(assignment.vehicle.attributes.get("max_speed_mps") or DEFAULT_SPEED_MPS)
    return ParcelSpec(
        id=f"{assignment.session_id}-{CARRIER}-{assignment.pk}",
        pickup=(delivery.pickup[0], delivery.pickup[1]),
        dropoff=(delivery.dropoff[0], delivery.dropoff[1]),
        altitude_m=CRUISE_ALTITUDE_M,
        load_altitude_m=LOAD_ALTITUDE_M,
        load_s=load_s(),
        drop_altitude_m=DROP_ALTITUDE_M,
        speed_mps=speed,
    )
