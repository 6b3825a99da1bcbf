"""What the carrier reports: recorded, then left to the next step (``workflow``)."""

from __future__ import annotations

from typing import Any

from django.db import transaction
from django.utils import timezone

from kinds.parcel_delivery.models import CARRIER, FINAL_DELIVERY, Delivery
from kinds.parcel_delivery.notifications import parcel_notices
from kinds.parcel_delivery.tasks import delivery_schedule
from services.kit import event_append, session_task_accepted
from services.models import Assignment

#: The carrier's mission events (agents/missions/parcel/, kind ``parcel``).
#: ``native_mission_refused``: the autopilot refused the plan, the agent flies it step
#: by step (logged: what the carrier would do without its agent changes).
#: ``native_mission_started``: the autopilot flies the plan itself (``within_s`` at most):
#: a vehicle gone silent meanwhile flies on, and is not replaced before that time.
PARCEL_EVENTS = frozenset(
    {
        "mission_progress",
        "native_mission_refused",
        "native_mission_started",
        "parcel_loaded",
        "payload_released",
        "mission_failed",
    }
)


def delivery_event(*, assignment: Assignment, name: str, data: dict[str, Any]) -> None:
    """Record one event the carrier reported and schedule a step. Reports from a
    vehicle that no longer carries the parcel are logged and otherwise ignored."""
    vehicle = str(assignment.vehicle_id)
    with transaction.atomic():
        delivery = Delivery.objects.select_for_update().filter(pk=assignment.session_id).first()
        entry = {"vehicle": vehicle, "role": assignment.role, **_clean(data)}
        if delivery is None:
            event_append(session=assignment.session, kind="agent_event", data=entry)
            return
        current = (
            assignment.active
            and assignment.role == CARRIER
            and delivery.state not in FINAL_DELIVERY
        )
        if name == "parcel_loaded" and current and delivery.loaded_at is None:
            delivery.loaded_at = timezone.now()
            # Collected: a handover point, if there was one, is behind it now.
            delivery.handover_lat = delivery.handover_lon = None
            delivery.save(update_fields=["loaded_at", "handover_lat", "handover_lon", "updated_at"])
            parcel_notices(delivery, moment="dispatched")
        elif name == "payload_released" and current and delivery.released_at is None:
            delivery.released_at = timezone.now()
            delivery.save(update_fields=["released_at", "updated_at"])
        if name != "mission_progress":  # progress moves the map, not the log
            event_append(session=assignment.session, kind=name, data=entry)
        delivery_schedule(delivery.pk)


def _clean(data: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in data.items() if k not in ("vehicle", "role")}


def delivery_task_accepted(*, assignment: Assignment) -> None:
    """The carrier accepted its task: the session is under way."""
    session_task_accepted(
        assignment=assignment, reason=f"{assignment.vehicle.name} accepted the parcel"
    )
    delivery_schedule(assignment.session_id)
