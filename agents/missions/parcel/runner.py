"""Flies the ``parcel`` mission: take off if needed, fly to ``pickup``, descend to
``load_altitude_m`` and wait ``load_s`` for the parcel to be put on board
(``parcel_loaded``), fly it to ``dropoff``, descend to ``drop_altitude_m``, release it
once (``payload_released``) and return home.

A vehicle whose autopilot flies missions itself (a MAVLink copter or boat) is handed the whole
of it as one plan (:func:`parcel_plan`): the autopilot then delivers and comes home
even if the agent dies. Otherwise the agent flies it step by step. A vehicle on the
surface (a boat: no ``take_off``, no altitude) sails it, armed first instead of
taking off, without the climbs and descents (the kit's steps skip them).
"""

from __future__ import annotations

from agents.missions.kit import MissionRunner
from agents.missions.parcel.spec import ParcelSpec
from agents.missions.plan import FlightPlan


def parcel_plan(m: ParcelSpec, *, speed_mps: float) -> FlightPlan:
    """The parcel mission as one plan, the same phases and events as the steps below:
    to the pickup, down, wait ``load_s`` (``parcel_loaded``), up, to the drop-off, down,
    release (``payload_released``), up, home."""
    return (
        FlightPlan()
        .take_off(m.altitude_m)
        .speed(speed_mps)
        .fly_to(m.pickup, m.altitude_m, phase="to_pickup")
        .fly_to(
            m.pickup, m.load_altitude_m, hold_s=m.load_s, phase="loading", event="parcel_loaded"
        )
        .fly_to(m.pickup, m.altitude_m)
        .fly_to(m.dropoff, m.altitude_m, phase="to_dropoff")
        .fly_to(m.dropoff, m.drop_altitude_m, phase="delivery")
        .release()
        .fly_to(m.dropoff, m.altitude_m)
        .return_home()
    )


class ParcelRunner(MissionRunner[ParcelSpec]):
    """See the module docstring."""

    async def fly(self) -> None:
        m = self.mission
        speed = self._within_declared("go_to_waypoint", {"speed_mps": m.speed_mps})
        plan = parcel_plan(m, speed_mps=float(speed.get("speed_mps", m.speed_mps)))
        if await self.fly_natively(plan):
            return
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
