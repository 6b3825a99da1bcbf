"""The survey's state machine: one idempotent step at a time.

    waiting_vehicle ──► flying ──► processing ──► done
          ▲               │ drone lost / low / failed: the next one resumes
          └───────────────┘ from the first photo not taken
    waiting_vehicle / flying ──► cancelled (the user ended it: a mosaic of what came)
    any state ──► failed

:func:`survey_advance` locks the survey, looks at the recorded facts (what the drone
reported, its status and battery, the photos stored) and does what the current state
calls for. It decides from the database only and commits everything with the state
that records it, so a step that runs twice finds the work done; a periodic timer
re-runs every unfinished survey.

The session ends when the last line is flown (the drone comes home by itself); the
photos may still be on their way then (a drone uploads them as its uplink allows), so
the mosaic is made once all of them are stored, or :func:`~kinds.survey.conf.
photos_wait_s` after the flight with those that came.
"""

from __future__ import annotations

import logging
from datetime import timedelta
from typing import Any

from django.db import transaction
from django.utils import timezone

from agents.missions.survey.spec import survey_photo_points
from kinds.survey.conf import photos_wait_s, survey_wait_s
from kinds.survey.events import PHOTO_NAME
from kinds.survey.geometry import Footprint, coverage
from kinds.survey.models import FINAL_SURVEY, SURVEYOR, Survey
from kinds.survey.mosaic import Placed, mosaic_build
from kinds.survey.planning import candidates, plan_for, plan_json, surveyor_assign
from services.kit import (
    FINAL,
    AssignmentError,
    assignment_release,
    camera_optics,
    session_close,
    session_transition,
    steps_run,
    task_redeploy_if_unaccepted,
    vehicle_task_deploy,
    vehicle_trouble,
    vehicles_unfit,
    workflow_state_set,
)
from services.models import Assignment, Session, SessionArtifact

log = logging.getLogger(__name__)

S = Survey.State


def survey_advance(session_id: Any) -> str | None:
    """Take the survey's next step, whatever its state; idempotent. Returns the state
    after the step, None for no such survey."""
    with transaction.atomic():
        survey = (
            Survey.objects.select_for_update(no_key=True)
            .select_related("session__service", "session__user")
            .filter(pk=session_id)
            .first()
        )
        if survey is None:
            return None
        if survey.state not in FINAL_SURVEY:
            _step(survey)
        elif survey.state == S.CANCELLED:
            # A cancelled survey's photos keep coming (the drone uploads what it took):
            # its mosaic shows them.
            _mosaic(survey)
        return str(survey.state)


def _step(survey: Survey) -> None:
    session = Session.objects.select_for_update(no_key=True).get(pk=survey.session_id)
    survey.session = session
    if survey.state == S.PROCESSING:
        _process(survey)
        return
    if session.state in FINAL:
        # Ended from outside: the user cancelled, a monitor stopped it, a task refused.
        if session.state == Session.State.FAILED:
            _set(survey, S.FAILED, f"the survey failed: {session.reason}")
        else:
            _set(survey, S.CANCELLED, f"cancelled: {session.reason}")
        _mosaic(survey)
        return
    if survey.flown_at is not None:
        _flown(survey)
    elif survey.state == S.WAITING_VEHICLE:
        _assign(survey)
    elif survey.state == S.FLYING:
        _supervise(survey)


def _set(survey: Survey, state: str, text: str, **data: Any) -> None:
    """Move the survey to ``state`` and log it (nothing when nothing changes)."""
    workflow_state_set(
        survey, session=survey.session, state=state, text=text, log_kind="survey_state", **data
    )


def _surveyor(survey: Survey) -> Assignment | None:
    return (
        Assignment.objects.filter(session_id=survey.pk, role=SURVEYOR, active=True)
        .select_related("vehicle__station", "session")
        .first()
    )


def _waited_too_long(survey: Survey) -> bool:
    limit = timedelta(seconds=survey_wait_s())
    if timezone.now() - survey.session.created_at < limit:
        return False
    minutes = limit.total_seconds() / 60
    session_close(session=survey.session, reason="no drone could fly it in time")
    _set(survey, S.FAILED, f"no drone could fly the survey within {minutes:g} min")
    return True


def _assign(survey: Survey) -> None:
    if _waited_too_long(survey):
        return
    try:
        with transaction.atomic():
            assignment = surveyor_assign(survey, exclude=vehicles_unfit(survey.session))
    except AssignmentError as exc:
        _set(survey, S.WAITING_VEHICLE, f"waiting for a drone: {exc}")
        return
    if survey.plan is None:
        # Planned for this drone's camera, and kept for any that takes over.
        optics = camera_optics(assignment.vehicle.attributes)
        assert optics is not None  # the surveyor role asks for it
        grid = plan_for(
            [(p[0], p[1]) for p in survey.polygon],
            optics,
            gsd_m=survey.gsd_cm / 100,
            front=survey.front_overlap,
            side=survey.side_overlap,
        )
        survey.plan = plan_json(grid)
        survey.photo_count = len(survey_photo_points(tuple(grid.lines), grid.spacing_m))
    survey.legs += 1
    survey.save(update_fields=["plan", "photo_count", "legs", "updated_at"])
    session = survey.session
    if session.state == Session.State.REQUESTED:
        session_transition(session=session, to=Session.State.ASSIGNED, reason="drone reserved")
    vehicle_task_deploy(session=session, assignment=assignment)
    where = "" if survey.next_photo == 0 else f" from photo {survey.next_photo + 1}"
    _set(
        survey,
        S.FLYING,
        f"{assignment.vehicle.name} flies the survey{where} "
        f"({survey.photo_count} photos from {survey.plan['altitude_m']:.0f} m)",
        vehicle=str(assignment.vehicle_id),
        vehicle_name=assignment.vehicle.name,
    )


def _supervise(survey: Survey) -> None:
    assignment = _surveyor(survey)
    if assignment is None:
        _set(survey, S.WAITING_VEHICLE, "looking for a drone")
        _assign(survey)
        return
    trouble = vehicle_trouble(assignment)
    if trouble is None:
        task_redeploy_if_unaccepted(session=survey.session, assignment=assignment)
        return
    assignment_release(session=survey.session, assignment=assignment, trouble=trouble)
    if not candidates(survey, exclude=[assignment.vehicle_id]):
        log.info("survey %s: no other drone can take it over now", survey.pk)
    _set(
        survey,
        S.WAITING_VEHICLE,
        f"{trouble.words}: the survey waits for another drone, from photo {survey.next_photo + 1}",
    )
    _assign(survey)


def _flown(survey: Survey) -> None:
    """The last line is flown: the session ends (the drone comes home by itself), the
    photos still on their way are awaited."""
    session_close(session=survey.session, reason="the area is photographed")
    _set(survey, S.PROCESSING, "photographed; the drone returns home; making the mosaic")
    _process(survey)


def photos(survey: Survey) -> list[SessionArtifact]:
    """The survey's photos the platform has, by index."""
    stored = SessionArtifact.objects.filter(
        session_id=survey.pk, stored_at__isnull=False, name__startswith="photo-"
    )
    return sorted((a for a in stored if PHOTO_NAME.match(a.name)), key=lambda a: a.name)


def footprints(survey: Survey, stored: list[SessionArtifact] | None = None) -> list[Footprint]:
    """Where each photo the platform has lies on the ground."""
    out = []
    for artifact in photos(survey) if stored is None else stored:
        meta = artifact.meta
        try:
            out.append(
                Footprint.of(
                    lat=float(meta["lat"]),
                    lon=float(meta["lon"]),
                    alt=float(meta.get("alt") or 0.0),
                    heading_deg=float(meta.get("heading_deg") or 0.0),
                    hfov_deg=float(meta["hfov_deg"]),
                    width=int(meta["width"]),
                    height=int(meta["height"]),
                )
            )
        except (KeyError, TypeError, ValueError):
            log.warning("survey %s: photo %s says not where it was taken", survey.pk, artifact.name)
    return out


def _process(survey: Survey) -> None:
    stored = photos(survey)
    waited = survey.flown_at is not None and timezone.now() - survey.flown_at >= timedelta(
        seconds=photos_wait_s()
    )
    if len(stored) < survey.photo_count and not waited:
        _set(
            survey,
            S.PROCESSING,
            f"photographed; {len(stored)} of {survey.photo_count} photos here, "
            "the others on their way",
        )
        return
    _mosaic(survey, stored)
    missing = survey.photo_count - len(stored)
    share = 100 * (survey.coverage or 0)
    text = f"the mosaic of {len(stored)} photos covers {share:.0f} % of the area"
    if missing > 0:
        text += f" ({missing} photos never came)"
    _set(survey, S.DONE, text)


def _mosaic(survey: Survey, stored: list[SessionArtifact] | None = None) -> None:
    """Make the mosaic of the photos the platform has (none: no mosaic)."""
    stored = photos(survey) if stored is None else stored
    placed = []
    for artifact in stored:
        try:
            placed.append(Placed.of(bytes(artifact.data or b""), artifact.meta))
        except (OSError, KeyError, TypeError, ValueError):
            log.warning("survey %s: photo %s cannot be placed", survey.pk, artifact.name)
    built = mosaic_build(placed)
    polygon = [(p[0], p[1]) for p in survey.polygon]
    survey.coverage = coverage(polygon, footprints(survey, stored)) if stored else 0.0
    if built is not None:
        survey.mosaic = built.png
        survey.mosaic_bounds = built.bounds
    survey.save(update_fields=["mosaic", "mosaic_bounds", "coverage", "updated_at"])


def surveys_advance_all() -> int:
    """One step for every unfinished survey (Celery beat): waiting for a drone, drones
    gone quiet, lost messages, photos late. Returns how many ran."""
    ids = Survey.objects.exclude(state__in=FINAL_SURVEY).values_list("pk", flat=True)
    return steps_run(list(ids), survey_advance, what="survey")
