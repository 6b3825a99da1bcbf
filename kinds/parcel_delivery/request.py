"""Requesting a parcel delivery: two points, a weight, who receives it.

:func:`params_clean` validates what was asked (both points on land, for a drone, or
both on the water, where the boat may take it); :func:`parcel_request` checks that a
carrier of the fleet could ever take it (:func:`delivery_feasible`: the weight, and the
trip from its station and back on a full battery), then opens the delivery. What no
carrier can ever take is refused at once, saying what would work; a parcel whose
carrier is busy is accepted and waits.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from django.core.exceptions import ValidationError
from django.core.validators import EmailValidator, URLValidator
from django.db import transaction

from accounts.users import User
from agents.geo import distance_m
from agents.geography import is_water
from kinds.parcel_delivery.models import KIND, Delivery
from kinds.parcel_delivery.planning import (
    MAX_TRIP_M,
    MAX_WEIGHT_KG,
    carrier_role_for,
    over_water,
    trip_work_m,
)
from kinds.parcel_delivery.tasks import delivery_schedule
from services.kit import Reach, RequestError, event_append, km, role_capable, session_open, trip_m
from services.models import Service, Session

#: The closest pickup and drop-off may be: nearer, it is not a delivery.
MIN_TRIP_M = 20.0


def _point(value: Any, field: str) -> tuple[float, float]:
    if not isinstance(value, Mapping) or set(value) - {"lat", "lon"} or len(value) != 2:
        raise RequestError('must be {"lat": ..., "lon": ...}', field=field)
    lat, lon = value["lat"], value["lon"]
    for name, number, limit in (("lat", lat, 90), ("lon", lon, 180)):
        if (
            isinstance(number, bool)
            or not isinstance(number, int | float)
            or not math.isfinite(number)
            or abs(number) > limit
        ):
            raise RequestError(
                f"must be a number from {-limit} to {limit}", field=f"{field}.{name}"
            )
    return (float(lat), float(lon))


def params_clean(params: Mapping[str, Any]) -> dict[str, Any]:
    """A delivery request's ``params``, validated (the one validation for the portal's
    form and the API); raises RequestError naming the field."""
    unknown = sorted(set(params) - {"pickup", "dropoff", "weight_kg", "recipient"})
    if unknown:
        raise RequestError("unknown field", field=f"params.{unknown[0]}")
    for name in ("pickup", "dropoff", "weight_kg"):
        if name not in params:
            raise RequestError("is required", field=f"params.{name}")
    pickup = _point(params["pickup"], "params.pickup")
    dropoff = _point(params["dropoff"], "params.dropoff")
    trip = distance_m(pickup, dropoff)
    if not MIN_TRIP_M <= trip <= MAX_TRIP_M:
        raise RequestError(
            f"is {trip:.0f} m from the pickup; a delivery goes {MIN_TRIP_M:g} m to "
            f"{MAX_TRIP_M / 1000:g} km",
            field="params.dropoff",
        )
    if is_water(*pickup) != is_water(*dropoff):
        # A drone cannot collect a parcel from the water, nor drop one into it; a
        # boat cannot reach a point on land.
        wet, field = (
            ("pickup", "params.pickup") if is_water(*pickup) else ("drop-off", "params.dropoff")
        )
        raise RequestError(
            f"the {wet} is on the water and the other point on land: a parcel goes from "
            "land to land (by drone) or from water to water (by boat)",
            field=field,
        )
    weight = params["weight_kg"]
    if (
        isinstance(weight, bool)
        or not isinstance(weight, int | float)
        or not 0 < weight <= MAX_WEIGHT_KG
    ):
        raise RequestError(
            f"must be more than 0 and at most {MAX_WEIGHT_KG:g} kg", field="params.weight_kg"
        )
    recipient = params.get("recipient") or {}
    if not isinstance(recipient, Mapping):
        raise RequestError("must be an object", field="params.recipient")
    extra = sorted(set(recipient) - {"name", "email", "webhook"})
    if extra:
        raise RequestError("unknown field", field=f"params.recipient.{extra[0]}")
    cleaned_recipient: dict[str, str] = {}
    for name, check, limit in (
        ("name", None, 100),
        ("email", EmailValidator(), 254),
        ("webhook", URLValidator(schemes=["http", "https"]), 300),
    ):
        value = recipient.get(name)
        if value in (None, ""):
            continue
        if not isinstance(value, str) or len(value) > limit:
            raise RequestError(
                f"must be text of at most {limit} characters", field=f"params.recipient.{name}"
            )
        if check is not None:
            try:
                check(value)
            except ValidationError:
                raise RequestError(
                    f"is not a valid {name}", field=f"params.recipient.{name}"
                ) from None
        cleaned_recipient[name] = value
    return {
        "pickup": {"lat": pickup[0], "lon": pickup[1]},
        "dropoff": {"lat": dropoff[0], "lon": dropoff[1]},
        "weight_kg": float(weight),
        "recipient": cleaned_recipient,
    }


def _payload(reach: Reach) -> float:
    return float(reach.attributes.get("max_payload_kg") or 0.0)


def delivery_feasible(
    *,
    service: Service,
    pickup: tuple[float, float],
    dropoff: tuple[float, float],
    weight_kg: float,
    water: bool,
) -> None:
    """Raises RequestError, naming the field and what would work, when no carrier of
    the fleet could ever take this parcel: none carries the weight (between points on
    land, only aircraft), or none has the range for the trip from its station, to the
    pickup, to the drop-off and back, on a full battery."""
    capable = role_capable(carrier_role_for(service, weight_kg=weight_kg, over_water=water))
    if not capable.vehicles:
        anyweight = role_capable(carrier_role_for(service, weight_kg=None, over_water=water))
        if not anyweight.vehicles:
            raise RequestError(f"no parcel can be carried: {anyweight.unmet}", field="service")
        heaviest = max(anyweight.vehicles, key=_payload)
        how = "between two points on the water" if water else "by air"
        text = (
            f"no vehicle carries {weight_kg:g} kg {how}: the heaviest parcel is "
            f"{_payload(heaviest):g} kg ({heaviest.name})"
        )
        if not water:
            boats = role_capable(carrier_role_for(service, weight_kg=weight_kg, over_water=True))
            if boats.vehicles:
                boat = max(boats.vehicles, key=_payload)
                text += (
                    f"; {boat.name} carries up to {_payload(boat):g} kg between two points "
                    "on the water"
                )
        raise RequestError(text, field="params.weight_kg")
    work = trip_work_m(pickup, dropoff)
    if any(v.fits(trip_m(v, pickup, work)) for v in capable.vehicles):
        return
    # Closest to managing it: the one whose reach falls shortest of the pickup.
    best = max(capable.vehicles, key=lambda v: v.radius_m(work) - distance_m(v.home, pickup))
    if best.radius_m(work) <= 0:
        longest = max(capable.vehicles, key=lambda v: v.range_m)
        raise RequestError(
            f"the trip is too long: {longest.name} carries a parcel at most about "
            f"{km(longest.range_m / 2)} from its pickup and back",
            field="params.dropoff",
        )
    raise RequestError(
        f"parcels on a {km(distance_m(pickup, dropoff))} trip can be picked up within "
        f"{km(best.radius_m(work))} of {best.station} ({best.name} on a full charge); this "
        f"pickup is {km(distance_m(best.home, pickup))} from it",
        field="params.pickup",
    )


def parcel_request(*, user: User, service: Service, params: Mapping[str, Any]) -> Session:
    """Open a delivery of ``params`` (cleaned by :func:`params_clean`) and start its
    workflow. Raises services.sessions.matching.AssignmentError when the user may not use the
    service or is at its session limit; RequestError for another kind of service, or
    a parcel no carrier of the fleet could ever take (:func:`delivery_feasible`)."""
    if service.kind != KIND:
        raise RequestError(f"{service.name!r} is not a parcel delivery service", field="service")
    pickup = (params["pickup"]["lat"], params["pickup"]["lon"])
    dropoff = (params["dropoff"]["lat"], params["dropoff"]["lon"])
    recipient = params.get("recipient") or {}
    water = over_water(pickup, dropoff)
    delivery_feasible(
        service=service,
        pickup=pickup,
        dropoff=dropoff,
        weight_kg=float(params["weight_kg"]),
        water=water,
    )
    with transaction.atomic():
        session = session_open(
            user=user, service=service, target=pickup, params=dict(params)
        ).session
        delivery = Delivery.objects.create(
            session=session,
            pickup_lat=pickup[0],
            pickup_lon=pickup[1],
            dropoff_lat=dropoff[0],
            dropoff_lon=dropoff[1],
            weight_kg=params["weight_kg"],
            over_water=water,
            recipient_name=recipient.get("name", ""),
            recipient_email=recipient.get("email", ""),
            recipient_webhook=recipient.get("webhook", ""),
            status_text="looking for a vehicle",
        )
        event_append(
            session=session,
            kind="delivery_planned",
            data={
                "trip_m": round(distance_m(pickup, dropoff)),
                "weight_kg": delivery.weight_kg,
                "over_water": delivery.over_water,
            },
        )
        delivery_schedule(delivery.pk)
    return session
