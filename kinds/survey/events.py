"""What the surveyor reports, and the photos that reach the platform: recorded, then
left to the next step (``workflow``)."""

from __future__ import annotations

import re
from typing import Any

from django.db import transaction
from django.utils import timezone

from kinds.survey.models import SURVEYOR, Survey
from kinds.survey.tasks import survey_schedule
from services.kit import event_append, session_task_accepted
from services.models import Assignment, SessionArtifact

#: The surveyor's mission events (agents/missions/survey/, kind ``survey``).
#: ``native_mission_refused``: the autopilot refused the lines, the agent flies them place
#: to place (logged: what the drone would do without its agent changes).
#: ``native_mission_started``: the autopilot flies the plan itself (``within_s`` at most):
#: a vehicle gone silent meanwhile flies on, and is not replaced before that time.
SURVEY_EVENTS = frozenset(
    {
        "mission_progress",
        "native_mission_refused",
        "native_mission_started",
        "photo_taken",
        "photo_missed",
        "survey_flown",
        "mission_failed",
    }
)
#: The file name of a survey photo (agents/missions/survey/runner.py, photo_name).
PHOTO_NAME = re.compile(r"^photo-(\d{4,})\.jpg$")


def survey_event(*, assignment: Assignment, name: str, data: dict[str, Any]) -> None:
    """Record one event the surveyor reported and schedule a step. Reports from a drone
    that no longer flies the survey are logged and otherwise ignored."""
    with transaction.atomic():
        survey = Survey.objects.select_for_update().filter(pk=assignment.session_id).first()
        entry = {"vehicle": str(assignment.vehicle_id), "role": assignment.role, **data}
        if survey is None:
            event_append(session=assignment.session, kind="agent_event", data=entry)
            return
        current = (
            assignment.active
            and assignment.role == SURVEYOR
            and survey.state == Survey.State.FLYING
        )
        if name == "photo_taken" and current and isinstance(data.get("index"), int):
            survey.next_photo = max(survey.next_photo, min(data["index"] + 1, survey.photo_count))
            survey.save(update_fields=["next_photo", "updated_at"])
        elif name == "survey_flown" and current and survey.flown_at is None:
            survey.flown_at = timezone.now()
            survey.save(update_fields=["flown_at", "updated_at"])
        # Progress and each photo move the map, not the log (the photo's arrival is
        # logged by the core, with its digest).
        if name not in ("mission_progress", "photo_taken"):
            event_append(session=assignment.session, kind=name, data=entry)
        survey_schedule(survey.pk)


def survey_photo_received(*, artifact: SessionArtifact) -> None:
    """A photo reached the platform (stored by the core): the map and the mosaic's step
    take it from there."""
    if not PHOTO_NAME.match(artifact.name):
        return
    state = Survey.objects.filter(pk=artifact.session_id).values_list("state", flat=True).first()
    # A cancelled survey's mosaic takes the photos that come late; a done one is done.
    if state is not None and state not in (Survey.State.DONE, Survey.State.FAILED):
        survey_schedule(artifact.session_id)


def survey_task_accepted(*, assignment: Assignment) -> None:
    """The surveyor accepted its task: the session is under way."""
    session_task_accepted(
        assignment=assignment, reason=f"{assignment.vehicle.name} accepted the survey"
    )
    survey_schedule(assignment.session_id)
