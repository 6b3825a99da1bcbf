"""The ``delivery`` mission's spec: drop a payload (a life ring) over a point."""

from __future__ import annotations

from agents.missions.spec import Altitude, LatLon, LowAltitude, MissionSpec, Speed, spec_invalid


class DeliverySpec(MissionSpec, frozen=True, kw_only=True, tag="delivery"):
    """Fly to ``target`` at ``altitude_m``, descend to ``drop_altitude_m``, release the
    payload once, climb back and hold."""

    target: LatLon
    altitude_m: Altitude
    drop_altitude_m: LowAltitude = 5.0
    speed_mps: Speed = 10.0

    def check(self) -> None:
        if self.drop_altitude_m > self.altitude_m:
            raise spec_invalid("drop_altitude_m", "must not be above altitude_m")
