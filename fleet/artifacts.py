"""Who keeps the files missions upload (``artifact`` chunks: the photos a mission takes): an
explicit interface, as for flight records (:mod:`fleet.records`).

``fleet`` receives the chunks on the uplink but does not own sessions; the app that owns
them registers its keeper here when it starts (services.apps), and the uplink calls it
for each chunk and answers the agent with its outcome (an ``ack``).
"""

from __future__ import annotations

from typing import Any, Protocol

from agents.protocol.messages import Artifact
from fleet.records import RecordOutcome


class ArtifactKeeper(Protocol):
    def __call__(self, *, vehicle_id: Any, message: Artifact) -> RecordOutcome:
        """Keep chunk ``message`` from the agent of ``vehicle_id`` (called from a worker
        thread; may use the ORM; raises only when the database cannot be reached)."""
        ...


_keeper: list[ArtifactKeeper] = []


def artifact_keeper_set(keeper: ArtifactKeeper) -> None:
    """Register the keeper of mission files (replacing any before it)."""
    _keeper[:] = [keeper]


def artifact_keep(*, vehicle_id: Any, message: Artifact) -> RecordOutcome:
    """Hand ``message`` to the registered keeper; refused when there is none."""
    if not _keeper:
        return RecordOutcome(ok=False, detail="this platform keeps no mission files")
    return _keeper[0](vehicle_id=vehicle_id, message=message)
