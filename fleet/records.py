"""Who keeps the flight-record batches agents upload: an explicit interface.

``fleet`` receives the ``record`` frames on the uplink but does not own sessions, and
must not import ``services``; the app that owns them registers its keeper here when it
starts (services.apps), and the uplink calls it for each batch and answers the agent
with its outcome (an ``ack``). One keeper, named in one place, instead of a signal that
would need exactly one receiver to mean anything.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

from agents.protocol.messages import Record


@dataclass(frozen=True)
class RecordOutcome:
    """What the agent is told of its batch: ``ok`` (stored, or already stored), else
    refused for good with ``detail``."""

    ok: bool
    detail: str = ""


class RecordKeeper(Protocol):
    def __call__(self, *, vehicle_id: Any, message: Record) -> RecordOutcome:
        """Store ``message`` from the agent of ``vehicle_id`` (called from a worker
        thread; may use the ORM; raises only when the database cannot be reached)."""
        ...


_keeper: list[RecordKeeper] = []


def record_keeper_set(keeper: RecordKeeper) -> None:
    """Register the keeper of flight records (replacing any before it)."""
    _keeper[:] = [keeper]


def record_keep(*, vehicle_id: Any, message: Record) -> RecordOutcome:
    """Hand ``message`` to the registered keeper; refused when there is none (a
    platform without the sessions app keeps no records)."""
    if not _keeper:
        return RecordOutcome(ok=False, detail="this platform keeps no flight records")
    return _keeper[0](vehicle_id=vehicle_id, message=message)
