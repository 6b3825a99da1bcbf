"""The vehicle classes the MAVLink integration drives, and their autopilots' modes.

ArduPilot builds one firmware per class of vehicle and each numbers its modes its own
way (``custom_mode`` in HEARTBEAT and DO_SET_MODE). The tables are written out here,
without pymavlink, so that the options and the vocabulary can be read without it; a
test checks them against pymavlink's own (``mode_mapping_acm``, ``mode_mapping_rover``).

=========  ==========  ======================================  =========================
class      firmware    MAV_TYPE in its heartbeat               hold / stop
=========  ==========  ======================================  =========================
copter     ArduCopter  2 QUADROTOR (also 3, 4, 13, 14, 15)     BRAKE, else LOITER
rover      ArduRover   10 GROUND_ROVER (FRAME_CLASS 1)         HOLD (it stops)
boat       ArduRover   11 SURFACE_BOAT (FRAME_CLASS 2)         LOITER (HOLD drifts)
=========  ==========  ======================================  =========================
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

#: ArduCopter's flight modes (ArduCopter/mode.h), custom_mode number -> name.
COPTER_MODES: Mapping[int, str] = {
    0: "STABILIZE",
    1: "ACRO",
    2: "ALT_HOLD",
    3: "AUTO",
    4: "GUIDED",
    5: "LOITER",
    6: "RTL",
    7: "CIRCLE",
    8: "POSITION",
    9: "LAND",
    10: "OF_LOITER",
    11: "DRIFT",
    13: "SPORT",
    14: "FLIP",
    15: "AUTOTUNE",
    16: "POSHOLD",
    17: "BRAKE",
    18: "THROW",
    19: "AVOID_ADSB",
    20: "GUIDED_NOGPS",
    21: "SMART_RTL",
    22: "FLOWHOLD",
    23: "FOLLOW",
    24: "ZIGZAG",
    25: "SYSTEMID",
    26: "AUTOROTATE",
    27: "AUTO_RTL",
    28: "TURTLE",
    29: "RATE_ACRO",
}

#: ArduRover's driving modes (Rover/mode.h), shared by rovers and boats.
ROVER_MODES: Mapping[int, str] = {
    0: "MANUAL",
    1: "ACRO",
    2: "LEARNING",
    3: "STEERING",
    4: "HOLD",
    5: "LOITER",
    6: "FOLLOW",
    7: "SIMPLE",
    8: "DOCK",
    9: "CIRCLE",
    10: "AUTO",
    11: "RTL",
    12: "SMART_RTL",
    15: "GUIDED",
    16: "INITIALISING",
}

#: MAV_TYPE values (common.xml).
MAV_TYPE_QUADROTOR = 2
MAV_TYPE_GROUND_ROVER = 10
MAV_TYPE_SURFACE_BOAT = 11


@dataclass(frozen=True)
class VehicleClass:
    """One class of vehicle: its firmware's modes, the MAV_TYPEs its autopilot may
    report, whether it flies, and which mode holds it where it is."""

    name: str
    firmware: str
    mav_types: frozenset[int]
    modes: Mapping[int, str]
    flies: bool
    hold_mode: str

    def mode_number(self, name: str) -> int:
        """The custom_mode of mode ``name``; KeyError for a mode this firmware lacks."""
        for number, mode in self.modes.items():
            if mode == name:
                return number
        raise KeyError(f"{self.firmware} has no mode {name}")

    def mode_name(self, number: int | None) -> str | None:
        """``GUIDED`` for this firmware's number; ``MODE_<n>`` for an unknown one."""
        if number is None:
            return None
        return self.modes.get(number, f"MODE_{number}")


COPTER = VehicleClass(
    name="copter",
    firmware="ArduCopter",
    # quad, coaxial, hexa, octo, tri, dodeca: ArduCopter's frames.
    mav_types=frozenset({2, 3, 4, 13, 14, 15, 29}),
    modes=COPTER_MODES,
    flies=True,
    hold_mode="BRAKE",
)
ROVER = VehicleClass(
    name="rover",
    firmware="ArduRover",
    mav_types=frozenset({MAV_TYPE_GROUND_ROVER}),
    modes=ROVER_MODES,
    flies=False,
    hold_mode="HOLD",
)
BOAT = VehicleClass(
    name="boat",
    firmware="ArduRover",
    mav_types=frozenset({MAV_TYPE_SURFACE_BOAT}),
    modes=ROVER_MODES,
    flies=False,
    # HOLD stops the motors: a rover stands, a boat drifts. LOITER holds the position.
    hold_mode="LOITER",
)

#: The classes by the name the ``vehicle_class`` option gives.
VEHICLE_CLASSES: Mapping[str, VehicleClass] = {c.name: c for c in (COPTER, ROVER, BOAT)}
