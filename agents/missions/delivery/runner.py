"""Flies the ``delivery`` mission: take off if needed, fly to ``target`` at
``altitude_m`` (``transit``), descend to ``drop_altitude_m`` (``delivery``), release the
payload once (``payload_released``), climb back and hold there (``hold``): it does not
go home; the platform sends the vehicle its next task.

A vehicle whose autopilot flies missions itself (a MAVLink copter or boat) is handed the
whole of it as one plan (:func:`delivery_plan`), ending in a hold the autopilot keeps
(AUTO) after the runner has ended: if the agent dies, the autopilot's own fail-safe
decides what follows (see docs/missions.md). Otherwise the agent flies it step by step.
A vehicle on the surface (a boat: no ``take_off``, no altitude) sails it, armed first
instead of taking off, without the descent and the climb (the kit's steps skip them).
"""

from __future__ import annotations

from agents.missions.delivery.spec import DeliverySpec
from agents.missions.kit import MissionRunner
from agents.missions.plan import FlightPlan


def delivery_plan(m: DeliverySpec, *, speed_mps: float) -> FlightPlan:
    """The delivery as one plan, the same phases and events as the steps below: to the
    target, down, release (``payload_released``), up, hold there."""
    return (
        FlightPlan()
        .take_off(m.altitude_m)
        .speed(speed_mps)
        .fly_to(m.target, m.altitude_m, phase="transit")
        .fly_to(m.target, m.drop_altitude_m, phase="delivery")
        .release()
        .fly_to(m.target, m.altitude_m)
        .hold(phase="hold")
    )


class DeliveryRunner(MissionRunner[DeliverySpec]):
    """See the module docstring."""

    async def fly(self) -> None:
        m = self.mission
        speed = self._within_declared("go_to_waypoint", {"speed_mps": m.speed_mps})
        plan = delivery_plan(m, speed_mps=float(speed.get("speed_mps", m.speed_mps)))
        if await self.fly_natively(plan):
            return
        await self.take_off_if_needed(m.altitude_m)
        self.progress("transit")
        await self.fly_to(m.target, m.altitude_m, speed=m.speed_mps, settle=True)
        self.progress("delivery")
        await self.release_over(m.target, m.altitude_m, m.drop_altitude_m, m.speed_mps)
        self.progress("hold")
