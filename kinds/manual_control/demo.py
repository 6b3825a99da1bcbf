"""Manual control in the demo world: one service per kind of demo vehicle a person
can drive, each allowing exactly its vehicles' commands."""

from __future__ import annotations

from typing import Any

from fleet.models import VehicleType
from services.kit import (
    BOAT_COMMANDS,
    CAR_COMMANDS,
    QUADCOPTER_COMMANDS,
    VTOL_COMMANDS,
    DemoService,
    command_names,
)
from services.models import Service

K = VehicleType.Kind
A = VehicleType.Adapter

#: Every manual service: a 500 ms link-loss fail-safe and the latency limits.
_LINK: dict[str, Any] = {
    "link_loss_timeout_ms": 500,
    "latency_soft_ms": 150,
    "latency_hard_ms": 400,
}


def demo_services() -> dict[str, DemoService]:
    """Drive a car, fly a drone, fly the VTOL, steer the boat."""
    return {
        "drive-car": DemoService(
            fields={
                **_LINK,
                "name": "Manual control of a car",
                "description": "Drive a robot car on campus from the browser, with live video.",
                "allowed_commands": command_names(CAR_COMMANDS),
                "failsafe_action": Service.Failsafe.STOP,
                "session_time_limit_s": 900,
                "max_speed_mps": 1.5,
            },
            roles={"vehicle": {"kinds": [K.GROUND], "adapters": [A.CAR], "cameras": ["rgb"]}},
        ),
        "fly-drone": DemoService(
            fields={
                **_LINK,
                "name": "Manual control of a drone",
                "description": "Fly a quadcopter inside a geofence around its station.",
                # Listed explicitly so a payload drone matched by this role cannot drop
                # its buoy during a joyride.
                "allowed_commands": command_names(QUADCOPTER_COMMANDS),
                "failsafe_action": Service.Failsafe.RETURN_TO_HOME,
                "session_time_limit_s": 600,
                "max_altitude_m": 30,
                "geofence_radius_m": 200,
            },
            roles={"vehicle": {"kinds": [K.AERIAL], "adapters": [A.MAVLINK], "cameras": ["rgb"]}},
        ),
        "fly-vtol": DemoService(
            fields={
                **_LINK,
                "name": "Manual control of the VTOL",
                "description": "Fly the VTOL plane with two virtual sticks.",
                "allowed_commands": command_names(VTOL_COMMANDS),
                "failsafe_action": Service.Failsafe.LAND,
                "session_time_limit_s": 600,
                "max_altitude_m": 60,
                "geofence_radius_m": 500,
            },
            roles={"vehicle": {"kinds": [K.HYBRID], "adapters": [A.SPEKTRUM], "cameras": ["rgb"]}},
        ),
        "drive-boat": DemoService(
            fields={
                **_LINK,
                "name": "Manual control of a boat",
                "description": "Steer a boat off Costa Nova beach, inside a geofence.",
                # The release hook is the rescue's and the parcels': not for a joyride.
                "allowed_commands": [
                    name for name in command_names(BOAT_COMMANDS) if name != "release_payload"
                ],
                # A boat cannot land: on link loss it sails home, which is also what
                # its autopilot's own fail-safe does (FS_ACTION 1) if the agent dies.
                "failsafe_action": Service.Failsafe.RETURN_TO_HOME,
                "session_time_limit_s": 900,
                "max_speed_mps": 3,
                "geofence_radius_m": 500,
            },
            roles={"vehicle": {"kinds": [K.AQUATIC], "adapters": [A.MAVLINK], "cameras": ["rgb"]}},
        ),
    }
