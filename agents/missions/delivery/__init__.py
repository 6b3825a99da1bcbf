"""The ``delivery`` mission: drop a payload over a point; see README.md."""

from __future__ import annotations

from typing import TYPE_CHECKING

from agents.missions.delivery.spec import DeliverySpec
from agents.missions.registry import Mission

if TYPE_CHECKING:
    from agents.missions.delivery.runner import DeliveryRunner


def _runner() -> type[DeliveryRunner]:
    from agents.missions.delivery.runner import DeliveryRunner

    return DeliveryRunner


MISSION = Mission(
    name="delivery", title="Drop a payload over a point", spec=DeliverySpec, runner=_runner
)
