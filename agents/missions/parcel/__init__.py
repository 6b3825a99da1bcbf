"""The ``parcel`` mission: carry a parcel from a pickup to a drop-off; see README.md."""

from __future__ import annotations

from typing import TYPE_CHECKING

from agents.missions.parcel.spec import ParcelSpec
from agents.missions.registry import Mission

if TYPE_CHECKING:
    from agents.missions.parcel.runner import ParcelRunner


def _runner() -> type[ParcelRunner]:
    from agents.missions.parcel.runner import ParcelRunner

    return ParcelRunner


MISSION = Mission(
    name="parcel",
    title="Carry a parcel from a pickup to a drop-off",
    spec=ParcelSpec,
    runner=_runner,
)
