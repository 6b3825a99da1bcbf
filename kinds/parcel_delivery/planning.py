"""Choosing the vehicle that carries a parcel, and what the trip costs it.

The carrier is the service's ``carrier`` role, narrowed for the parcel: it must carry
the weight (``max_payload_kg``), have the range for pickup → drop-off → home, and it is
the one that arrives first (the role's selection). A boat may take it only when both
points are on water; anywhere else it flies.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable
from typing import Any

from agents.geo import distance_m
from agents.geography import is_water
from fleet.models import VehicleType
from kinds.parcel_delivery.models import CARRIER, Delivery
from services.kit import role_assign
from services.models import Assignment, Service, ServiceRole

#: The heaviest parcel and the longest trip a request may ask for.
MAX_WEIGHT_KG = 25.0
MAX_TRIP_M = 30_000.0
#: Flying height on the way, and near the ground to load and to drop.
CRUISE_ALTITUDE_M = 30.0
LOAD_ALTITUDE_M = 2.0
DROP_ALTITUDE_M = 3.0


def over_water(a: tuple[float, float], b: tuple[float, float]) -> bool:
    """Both points are known to be on water (the packaged land map; outside its
    regions nothing is known, and a parcel flies)."""
    return is_water(*a) and is_water(*b)


def carrier_role_for(service: Service, *, weight_kg: float | None, over_water: bool) -> ServiceRole:
    """``service``'s carrier role narrowed for a parcel of ``weight_kg`` (None: any
    weight) between two points on water (``over_water``: a boat may take it) or not
    (only aircraft): an unsaved copy."""
    role = service.roles.get(name=CARRIER)
    tight = copy.copy(role)
    if weight_kg is not None:
        minimums = dict(role.min_attributes or {})
        minimums["max_payload_kg"] = max(float(minimums.get("max_payload_kg", 0)), weight_kg)
        tight.min_attributes = minimums
    kinds = list(role.kinds) or [k.value for k in VehicleType.Kind]
    if not over_water:
        kinds = [k for k in kinds if k != VehicleType.Kind.AQUATIC]
    tight.kinds = kinds
    return tight


def carrier_role(delivery: Delivery) -> ServiceRole:
    """The service's carrier role, narrowed for this parcel (an unsaved copy)."""
    return carrier_role_for(
        delivery.session.service, weight_kg=delivery.weight_kg, over_water=delivery.over_water
    )


def trip_work_m(pickup: tuple[float, float], dropoff: tuple[float, float]) -> float:
    """:func:`trip_extra_m` of a parcel from ``pickup`` to ``dropoff``."""
    return 2 * distance_m(pickup, dropoff)


def trip_extra_m(delivery: Delivery) -> float:
    """The work after the pickup that must fit in the carrier's range: to the drop-off
    and, since matching measures the way home from the pickup, back to it (the way
    home from the drop-off is never longer than that)."""
    return trip_work_m(delivery.pickup, delivery.dropoff)


def carrier_assign(delivery: Delivery, *, exclude: Iterable[Any] = ()) -> Assignment:
    """Reserve the best carrier for the parcel where it waits now; raises
    services.sessions.matching.AssignmentError naming the unmet requirement."""
    return role_assign(
        session=delivery.session,
        role=carrier_role(delivery),
        target=delivery.pickup,
        extra_distance_m=trip_extra_m(delivery),
        exclude=exclude,
    )
