"""Flies the ``delivery`` mission: take off if needed, fly to ``target`` at
``altitude_m``, descend to ``drop_altitude_m``, release the payload once
(``payload_released``), climb back and hold."""

from __future__ import annotations

from agents.missions.delivery.spec import DeliverySpec
from agents.missions.kit import MissionRunner


class DeliveryRunner(MissionRunner[DeliverySpec]):
    """See the module docstring."""

    async def fly(self) -> None:
        m = self.mission
        await self.take_off_if_needed(m.altitude_m)
        self.progress("transit")
        await self.fly_to(m.target, m.altitude_m, speed=m.speed_mps, settle=True)
        self.progress("delivery")
        await self.release_over(m.target, m.altitude_m, m.drop_altitude_m, m.speed_mps)
        self.progress("hold")
