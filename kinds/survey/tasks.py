"""Celery tasks of the aerial survey: its steps and its timer. They keep no state of
their own, so a killed worker loses nothing and running one twice changes nothing."""

from __future__ import annotations

from typing import Any

from celery import shared_task
from django.conf import settings
from django.db import transaction

from iouv.celery import app


def survey_schedule(session_id: Any) -> None:
    """Run a step of the survey after the current transaction commits."""
    transaction.on_commit(lambda: survey_step.delay(str(session_id)), robust=True)


@shared_task(name="survey.step", acks_late=True)
def survey_step(session_id: str) -> str | None:
    """One step of a survey's workflow (idempotent)."""
    from kinds.survey.workflow import survey_advance

    return survey_advance(session_id)


@shared_task(name="survey.tick")
def surveys_tick() -> int:
    """Re-run every unfinished survey: timers, waiting, lost messages."""
    from kinds.survey.workflow import surveys_advance_all

    return surveys_advance_all()


@app.on_after_finalize.connect
def _schedule(sender, **kwargs) -> None:  # type: ignore[no-untyped-def]
    sender.add_periodic_task(settings.IOUV_MISSION_TICK_S, surveys_tick.s(), name="advance surveys")
