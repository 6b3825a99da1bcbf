"""The delivery's state machine: one idempotent step at a time.

    waiting_carrier ──► to_pickup ──► to_dropoff ──► delivered
          ▲                 │              │ carrier lost / low / failed: the next one
          └─────────────────┴──────────────┘ collects the parcel where it is
    any state ──► cancelled (the user ended the session) / failed

:func:`delivery_advance` locks the delivery, looks at the recorded facts (what the
carrier reported, its status and battery) and does what the current state calls for.
It decides from the database only and commits everything with the state that records
it, so a step that runs twice finds the work done; a periodic timer re-runs every
unfinished delivery.
"""

from __future__ import annotations

import logging
from datetime import timedelta
from typing import Any

from django.db import transaction
from django.utils import timezone

from kinds.parcel_delivery.conf import parcel_wait_s
from kinds.parcel_delivery.models import CARRIER, FINAL_DELIVERY, Delivery
from kinds.parcel_delivery.notifications import parcel_notices
from kinds.parcel_delivery.planning import carrier_assign, carrier_role, trip_extra_m
from services.kit import (
    FINAL,
    AssignmentError,
    assignment_release,
    role_capable,
    session_close,
    session_transition,
    steps_run,
    task_redeploy_if_unaccepted,
    trip_m,
    vehicle_task_deploy,
    vehicle_trouble,
    vehicles_unfit,
    waiting_words,
    workflow_state_set,
)
from services.models import Assignment, Session

log = logging.getLogger(__name__)

S = Delivery.State


def delivery_advance(session_id: Any) -> str | None:
    """Take the delivery's next step, whatever its state; idempotent. Returns the state
    after the step, None for no such delivery."""
    with transaction.atomic():
        delivery = (
            Delivery.objects.select_for_update(no_key=True)
            .select_related("session__service", "session__user")
            .filter(pk=session_id)
            .first()
        )
        if delivery is None:
            return None
        if delivery.state not in FINAL_DELIVERY:
            _step(delivery)
        return str(delivery.state)


def _step(delivery: Delivery) -> None:
    session = Session.objects.select_for_update(no_key=True).get(pk=delivery.session_id)
    delivery.session = session
    if session.state in FINAL:
        # Ended from outside: the user cancelled, a monitor stopped it, a task refused.
        if delivery.released_at is not None:
            _set(delivery, S.DELIVERED, "delivered")
        elif session.state == Session.State.FAILED:
            _set(delivery, S.FAILED, f"the delivery failed: {session.reason}")
        else:
            _set(delivery, S.CANCELLED, f"cancelled: {session.reason}")
        return
    if delivery.released_at is not None:
        _finish(delivery)
        return
    if delivery.state == S.WAITING_CARRIER:
        _assign(delivery)
    elif delivery.state in (S.TO_PICKUP, S.TO_DROPOFF):
        _supervise(delivery)


def _set(delivery: Delivery, state: str, text: str, **data: Any) -> None:
    """Move the delivery to ``state`` and log it (nothing when nothing changes)."""
    workflow_state_set(
        delivery,
        session=delivery.session,
        state=state,
        text=text,
        log_kind="delivery_state",
        **data,
    )


def _carrier(delivery: Delivery) -> Assignment | None:
    return (
        Assignment.objects.filter(session_id=delivery.pk, role=CARRIER, active=True)
        .select_related("vehicle__station", "session")
        .first()
    )


def _waited_too_long(delivery: Delivery) -> bool:
    limit = timedelta(seconds=parcel_wait_s())
    if timezone.now() - delivery.session.created_at < limit:
        return False
    minutes = limit.total_seconds() / 60
    _end(delivery, S.FAILED, f"no vehicle could take the parcel within {minutes:g} min")
    return True


def _assign(delivery: Delivery) -> None:
    if _waited_too_long(delivery):
        return
    try:
        with transaction.atomic():
            assignment = carrier_assign(delivery, exclude=vehicles_unfit(delivery.session))
    except AssignmentError as exc:
        _set(delivery, S.WAITING_CARRIER, f"waiting for a vehicle: {_waiting(delivery) or exc}")
        return
    session = delivery.session
    delivery.legs += 1
    delivery.save(update_fields=["legs", "updated_at"])
    if session.state == Session.State.REQUESTED:
        session_transition(session=session, to=Session.State.ASSIGNED, reason="carrier reserved")
    vehicle_task_deploy(session=session, assignment=assignment)
    aboard = delivery.loaded_at is not None
    where = "where the last one left it" if delivery.handover_lat is not None else "at the pickup"
    _set(
        delivery,
        S.TO_PICKUP,
        f"{assignment.vehicle.name} is on its way to collect the parcel {where}"
        if not aboard or delivery.handover_lat is not None
        else f"{assignment.vehicle.name} brings the parcel",
        vehicle=str(assignment.vehicle_id),
        vehicle_name=assignment.vehicle.name,
    )


def _waiting(delivery: Delivery) -> str:
    """Why the parcel waits for a carrier the fleet has (busy, offline, charging), with
    its place in the queue; "" when none of the fleet's could take it from here."""
    role = carrier_role(delivery)
    work = trip_extra_m(delivery)
    serving = [
        (carrier, trip)
        for carrier in role_capable(role, exclude=vehicles_unfit(delivery.session)).vehicles
        if carrier.fits(trip := trip_m(carrier, delivery.pickup, work))
    ]
    return waiting_words(session=delivery.session, role=role, serving=serving)


def _supervise(delivery: Delivery) -> None:
    assignment = _carrier(delivery)
    if assignment is None:
        _set(delivery, S.WAITING_CARRIER, "looking for a vehicle")
        _assign(delivery)
        return
    if delivery.loaded_at is not None and delivery.state == S.TO_PICKUP:
        _set(
            delivery,
            S.TO_DROPOFF,
            f"{assignment.vehicle.name} has the parcel, on its way to the drop-off",
            vehicle=str(assignment.vehicle_id),
        )
    trouble = vehicle_trouble(assignment)
    if trouble is None:
        task_redeploy_if_unaccepted(session=delivery.session, assignment=assignment)
        return
    assignment_release(session=delivery.session, assignment=assignment, trouble=trouble)
    words = trouble.words
    if delivery.loaded_at is not None:
        # The parcel is with the carrier that gave up: the next one collects it there.
        vehicle = assignment.vehicle
        vehicle.refresh_from_db(fields=["lat", "lon"])
        if vehicle.lat is not None and vehicle.lon is not None:
            delivery.handover_lat, delivery.handover_lon = vehicle.lat, vehicle.lon
        delivery.loaded_at = None
        delivery.save(update_fields=["handover_lat", "handover_lon", "loaded_at", "updated_at"])
        _set(delivery, S.WAITING_CARRIER, f"{words}: the parcel waits for another vehicle there")
    else:
        _set(delivery, S.WAITING_CARRIER, f"{words}: looking for another vehicle")
    _assign(delivery)


def _finish(delivery: Delivery) -> None:
    """Released at the drop-off: the recipient is told, the session ends (the carrier
    flies home on its own), the delivery is done."""
    parcel_notices(delivery, moment="delivered")
    _end(delivery, S.DELIVERED, "delivered; the vehicle returns to its station")


def _end(delivery: Delivery, state: str, text: str) -> None:
    session_close(session=delivery.session, reason=text)
    _set(delivery, state, text)


def deliveries_tick() -> int:
    """One step for every unfinished delivery (Celery beat): waiting for a vehicle,
    carriers gone quiet, lost messages. Returns how many ran."""
    ids = Delivery.objects.exclude(state__in=FINAL_DELIVERY).values_list("pk", flat=True)
    return steps_run(list(ids), delivery_advance, what="delivery")
