"""The ``parcel`` mission's spec: collect a parcel, carry it, release it, go home."""

from __future__ import annotations

from typing import Annotated, Final

from msgspec import Meta

from agents.missions.spec import Altitude, LatLon, LowAltitude, MissionSpec, Speed, spec_invalid

#: The longest a parcel may take to be put on board.
MAX_LOAD_S: Final = 600


class ParcelSpec(MissionSpec, frozen=True, kw_only=True, tag="parcel"):
    """Collect a parcel at ``pickup`` (descend to ``load_altitude_m``, wait ``load_s``),
    release it at ``dropoff`` from ``drop_altitude_m``, go home."""

    pickup: LatLon
    dropoff: LatLon
    altitude_m: Altitude
    load_altitude_m: LowAltitude = 2.0
    load_s: Annotated[float, Meta(ge=0, le=MAX_LOAD_S)] = 10.0
    drop_altitude_m: LowAltitude = 3.0
    speed_mps: Speed = 10.0

    def check(self) -> None:
        if self.load_altitude_m > self.altitude_m:
            raise spec_invalid("load_altitude_m", "must not be above altitude_m")
        if self.drop_altitude_m > self.altitude_m:
            raise spec_invalid("drop_altitude_m", "must not be above altitude_m")
