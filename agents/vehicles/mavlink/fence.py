"""The autopilot's own fence, set from a task's limits: the second line.

The agent keeps a vehicle inside its task's ceiling and geofence itself (the gate and
the envelope). Should the agent die, hang or lose its link to the autopilot, nothing of
that holds; ArduPilot's fence (``libraries/AC_Fence``) does, in the autopilot. So when
a task starts the agent sets it (:func:`fence_set`), a margin outside the agent's own
limits, so that the agent's envelope acts first and the autopilot catches what the
agent misses:

* ``FENCE_ALT_MAX`` (ArduCopter; FENCE_TYPE bit 0) = the ceiling + its margin
  (:func:`agents.envelope.band_for`: 20 %, at most 2 m). ArduCopter also keeps its own
  RTL ``FENCE_MARGIN`` (2 m) under it, so a return no longer climbs above the ceiling;
* the geofence: centred on home, ``FENCE_RADIUS`` (FENCE_TYPE bit 1) = its radius + its
  margin (20 %, at most 5 m); centred elsewhere, an inclusion circle of that radius
  (``MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION``, FENCE_TYPE bit 2) uploaded with the MAVLink
  mission protocol for ``MAV_MISSION_TYPE_FENCE`` (MISSION_COUNT, MISSION_REQUEST_INT,
  MISSION_ITEM_INT, MISSION_ACK); it replaces a fence the autopilot had uploaded;
* ``FENCE_ACTION`` from the task's fail-safe action: ArduCopter 1 (RTL, else LAND) for
  ``return_to_home``, 2 (LAND) for ``land``, 4 (BRAKE, else LAND) for ``stop``;
  ArduRover 1 (RTL, else HOLD) for ``return_to_home``, 2 (HOLD) for ``stop`` and
  ``land``;
* ``FENCE_ENABLE`` = 1, last.

The values the autopilot had are read first and put back when the task ends
(:func:`fence_clear`; an uploaded circle is cleared), but not when the agent stops:
then the fence is what is left to hold the vehicle.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field

from agents.envelope import ALTITUDE, GEOFENCE, band_for
from agents.geo import distance_m
from agents.vehicles.base import AdapterError
from agents.vehicles.mavlink.classes import VehicleClass
from agents.vehicles.mavlink.dialect import MAV
from agents.vehicles.mavlink.link import AutopilotLink
from agents.vehicles.mavlink.mission import MissionItem, items_upload

logger = logging.getLogger(__name__)

#: FENCE_TYPE bits.
TYPE_ALT_MAX, TYPE_CIRCLE, TYPE_POLYGON = 1, 2, 4
#: A geofence centred this close to home (m) is ArduPilot's home circle.
HOME_CENTRE_M = 1.0
#: FENCE_ACTION for a task's fail-safe action, per firmware.
COPTER_FENCE_ACTIONS = {"return_to_home": 1, "land": 2, "stop": 4}
ROVER_FENCE_ACTIONS = {"return_to_home": 1, "land": 2, "stop": 2}
#: What :func:`fence_set` changes, and :func:`fence_clear` puts back.
FENCE_PARAMS = ("FENCE_ENABLE", "FENCE_TYPE", "FENCE_ACTION", "FENCE_ALT_MAX", "FENCE_RADIUS")


@dataclass
class FenceState:
    """What the agent set, and what the autopilot had before (to put it back)."""

    previous: dict[str, float] = field(default_factory=dict)
    uploaded: bool = False


async def fence_set(
    link: AutopilotLink,
    vehicle_class: VehicleClass,
    action: str,
    *,
    max_altitude_m: float | None,
    geofence_center: tuple[float, float] | None,
    geofence_radius_m: float | None,
    home: tuple[float, float] | None,
    state: FenceState,
) -> tuple[dict[str, float], list[str]]:
    """Set the autopilot's fence from a task's limits (see the module docstring).
    Returns what was set (parameter -> value) and the problems in words ([]: all set).
    Never raises. With no limit the autopilot can hold, nothing is set."""
    values: dict[str, float] = {}
    types = 0
    if max_altitude_m is not None and vehicle_class.flies:
        types |= TYPE_ALT_MAX
        values["FENCE_ALT_MAX"] = round(
            max_altitude_m + band_for(ALTITUDE, max_altitude_m).margin, 2
        )
    circle: tuple[tuple[float, float], float] | None = None
    if geofence_center is not None and geofence_radius_m is not None:
        radius = round(geofence_radius_m + band_for(GEOFENCE, geofence_radius_m).margin, 2)
        if home is not None and distance_m(home, geofence_center) <= HOME_CENTRE_M:
            types |= TYPE_CIRCLE
            values["FENCE_RADIUS"] = radius
        else:
            types |= TYPE_POLYGON
            circle = (geofence_center, radius)
    if not types:
        return {}, []
    actions = COPTER_FENCE_ACTIONS if vehicle_class.flies else ROVER_FENCE_ACTIONS
    values["FENCE_TYPE"] = types
    values["FENCE_ACTION"] = actions.get(action, 1)
    problems: list[str] = []
    names = [n for n in FENCE_PARAMS if n != "FENCE_ALT_MAX" or vehicle_class.flies]
    if not state.previous:
        for name in names:
            try:
                state.previous[name] = await link.read_param(name)
            except AdapterError as exc:
                problems.append(f"could not read {name}: {exc}")
        if problems:
            state.previous.clear()
            return {}, problems  # an autopilot without a fence: nothing to set
    if circle is not None:
        try:
            await fence_upload(link, [circle])
            state.uploaded = True
        except AdapterError as exc:
            return {}, [f"could not upload the geofence: {exc}"]
    for name, value in {**values, "FENCE_ENABLE": 1}.items():
        try:
            took = await link.set_param(name, value)
        except AdapterError as exc:
            problems.append(f"could not set {name}: {exc}")
            continue
        if abs(took - value) > 0.01:
            problems.append(f"{name} is {took:g}, not {value:g}")
    return {**values, "FENCE_ENABLE": 1}, problems


async def fence_clear(link: AutopilotLink, state: FenceState) -> list[str]:
    """Put back what :func:`fence_set` changed (FENCE_ENABLE first) and clear an
    uploaded circle. Returns the problems in words. Never raises."""
    problems: list[str] = []
    previous, state.previous = state.previous, {}
    for name in sorted(previous, key=lambda n: n != "FENCE_ENABLE"):
        try:
            await link.set_param(name, previous[name])
        except AdapterError as exc:
            problems.append(f"could not put {name} back to {previous[name]:g}: {exc}")
    if state.uploaded:
        state.uploaded = False
        try:
            await fence_upload(link, [])
        except AdapterError as exc:
            problems.append(f"could not clear the uploaded geofence: {exc}")
    return problems


async def fence_upload(
    link: AutopilotLink, circles: list[tuple[tuple[float, float], float]]
) -> None:
    """Upload inclusion circles ((lat, lon), radius m) as the autopilot's fence (the
    mission protocol for MAV_MISSION_TYPE_FENCE, :func:`.mission.items_upload`); none
    clears it (MISSION_CLEAR_ALL). Raises AdapterError when the autopilot refuses
    (MISSION_ACK other than ACCEPTED), does not answer, or is lost."""
    items = [
        MissionItem(
            MAV.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, MAV.MAV_FRAME_GLOBAL,
            (radius, 0.0, 0.0, 0.0), lat, lon,
        )
        for (lat, lon), radius in circles
    ]  # fmt: skip
    await items_upload(link, MAV.MAV_MISSION_TYPE_FENCE, items, what="fence")


def fence_words(values: Mapping[str, float]) -> dict[str, float]:
    """What was set, for the ``autopilot_fence`` event."""
    return {name.lower().removeprefix("fence_"): value for name, value in values.items()}
