"""Celery tasks of the rescue: its steps and its timer (notices are the core's).

They keep no state of their own: every one reads the mission from the database, so a
killed worker loses nothing and running one twice changes nothing.
"""

from __future__ import annotations

from typing import Any

from celery import shared_task
from django.conf import settings
from django.db import transaction

from iouv.celery import app
from kinds.rescue_at_sea.workflow import mission_advance, missions_tick


def mission_schedule(session_id: Any) -> None:
    """Run a step of the mission after the current transaction commits."""
    transaction.on_commit(lambda: mission_step.delay(str(session_id)), robust=True)


@shared_task(name="rescue_at_sea.mission_step", acks_late=True)
def mission_step(session_id: str) -> str | None:
    """One step of a mission's workflow (idempotent: safe to run twice)."""
    return mission_advance(session_id)


@shared_task(name="rescue_at_sea.missions_tick")
def rescue_missions_tick() -> int:
    """Re-run every unfinished mission: timers, waiting, lost messages, notices."""
    return missions_tick()


@app.on_after_finalize.connect
def _schedule(sender, **kwargs) -> None:  # type: ignore[no-untyped-def]
    sender.add_periodic_task(
        settings.IOUV_MISSION_TICK_S, rescue_missions_tick.s(), name="advance rescues"
    )
