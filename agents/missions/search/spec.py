"""The ``search`` mission's spec: the lawnmower pattern a rescue drone flies."""

from __future__ import annotations

from typing import Annotated, Final

from msgspec import Meta

from agents.missions.spec import Altitude, LatLon, MissionSpec, Speed, spec_invalid

MAX_WAYPOINTS: Final = 2000


class SearchSpec(MissionSpec, frozen=True, kw_only=True, tag="search"):
    """Fly ``waypoints[start_index:]`` at ``altitude_m`` looking for a person; the first
    one seen at ``min_confidence`` or more is reported and the drone holds over them."""

    altitude_m: Altitude
    #: ``[lat, lon]`` of each turn of the pattern, in order.
    waypoints: Annotated[tuple[LatLon, ...], Meta(min_length=1, max_length=MAX_WAYPOINTS)]
    speed_mps: Speed = 10.0
    #: Where the pattern starts (a replacement drone re-flies its predecessor's leg).
    start_index: Annotated[int, Meta(ge=0)] = 0
    min_confidence: Annotated[float, Meta(ge=0, le=1)] = 0.6

    def check(self) -> None:
        last = len(self.waypoints) - 1
        if self.start_index > last:
            raise spec_invalid("start_index", f"an integer in [0, {last}], not {self.start_index}")
