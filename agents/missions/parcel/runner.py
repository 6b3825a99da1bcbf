"""Flies the ``parcel`` mission: take off if needed, fly to ``pickup``, descend to
``load_altitude_m`` and wait ``load_s`` for the parcel to be put on board
(``parcel_loaded``), fly it to ``dropoff``, descend to ``drop_altitude_m``, release it
once (``payload_released``) and return home.

A vehicle on the surface (a boat: no ``take_off``, no altitude) sails it, armed first
instead of taking off, without the climbs and descents (the kit's steps skip them).
"""

from __future__ import annotations

from agents.missions.kit import MissionRunner
from agents.missions.parcel.spec import ParcelSpec


class ParcelRunner(MissionRunner[ParcelSpec]):
    """See the module docstring."""

    async def fly(self) -> None:
        m = self.mission
        await self.take_off_if_needed(m.altitude_m)
        self.progress("to_pickup")
        await self.fly_to(m.pickup, m.altitude_m, speed=m.speed_mps, settle=True)
        self.progress("loading")
        await self.descend(m.pickup, m.altitude_m, m.load_altitude_m, m.speed_mps)
        await self.hold_for(m.load_s)
        self.report("parcel_loaded", **self.where())
        await self.climb(m.pickup, m.load_altitude_m, m.altitude_m, m.speed_mps)
        self.progress("to_dropoff")
        await self.fly_to(m.dropoff, m.altitude_m, speed=m.speed_mps, settle=True)
        self.progress("delivery")
        await self.release_over(m.dropoff, m.altitude_m, m.drop_altitude_m, m.speed_mps)
        await self.return_home()
