"""What a MAVLink vehicle offers users, by vehicle class: its commands and telemetry.

Light on purpose (no pymavlink): the platform reads the vocabulary from a config
through the integration (:func:`mavlink_commands`), as the adapter declares it. The
mapping of each command to MAVLink is in the adapters (:mod:`.copter`) and in
``docs/vehicles/``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from agents.vehicles.base import CommandSpec
from agents.vehicles.mavlink.config import MavlinkConfig

TELEMETRY_TOPICS = [
    "battery_level",
    "altitude",
    "location",
    "speed",
    "heading",
    "flight_mode",
    "is_armed",
    "number_of_gps_satellites",
    "autopilot_link",
    "gps_fix",
    "ekf_ok",
    "in_air",
]


def copter_vocabulary(config: MavlinkConfig) -> list[CommandSpec]:
    cfg = config
    speed = {
        "speed_mps": {
            "type": "number",
            "min": 0.1,
            "max": cfg.max_speed_mps,
            "default": cfg.move_speed_mps,
            "unit": "m/s",
        }
    }
    angle = {
        "angle_deg": {
            "type": "number",
            "min": 1,
            "max": 180,
            "default": cfg.rotate_default_deg,
            "unit": "deg",
        }
    }

    def move(name: str, text: str, group: str, key: str) -> CommandSpec:
        return CommandSpec(
            name, text, group=group, args=speed, motion=True, speed_arg="speed_mps", key=key
        )

    return [
        CommandSpec("arm", "Arm the motors (in GUIDED)", group="setup"),
        CommandSpec("disarm", "Disarm the motors (on the ground)", group="setup"),
        CommandSpec(
            "take_off",
            "Take off and hover",
            group="setup",
            args={
                "altitude_m": {
                    "type": "number",
                    "min": 1,
                    "max": cfg.max_takeoff_m,
                    "default": cfg.takeoff_default_m,
                    "unit": "m",
                }
            },
            key="t",
        ),
        move("up", "Climb", "left", "w"),
        move("down", "Descend", "left", "s"),
        CommandSpec("rotate_left", "Yaw left", group="left", args=angle, motion=True, key="a"),
        CommandSpec("rotate_right", "Yaw right", group="left", args=angle, motion=True, key="d"),
        move("front", "Fly forward", "right", "ArrowUp"),
        move("back", "Fly backward", "right", "ArrowDown"),
        move("left", "Fly left", "right", "ArrowLeft"),
        move("right", "Fly right", "right", "ArrowRight"),
        CommandSpec("stop", "Stop and hover", group="middle", key="Space"),
        CommandSpec("land", "Land where it is", group="middle", key="l"),
        CommandSpec(
            "return_to_home", "Fly back to the take-off point and land", group="middle", key="h"
        ),
        *(
            [CommandSpec("release_payload", "Drop the payload", group="mission", key="r")]
            if cfg.payload is not None
            else []
        ),
        CommandSpec(
            "go_to_waypoint",
            "Fly to a position",
            group="mission",
            args={
                "lat": {"type": "number", "min": -90, "max": 90, "unit": "deg"},
                "lon": {"type": "number", "min": -180, "max": 180, "unit": "deg"},
                "alt_m": {"type": "number", "min": 1, "max": cfg.max_takeoff_m, "unit": "m"},
                # 0: the autopilot's own cruise speed (WPNAV_SPEED).
                "speed_mps": {
                    "type": "number",
                    "min": 0,
                    "max": cfg.max_speed_mps,
                    "default": 0,
                    "unit": "m/s",
                },
            },
        ),
    ]


def mavlink_vocabulary(config: MavlinkConfig) -> list[CommandSpec]:
    """The commands of the vehicle class ``config`` names."""
    return copter_vocabulary(config)


def mavlink_commands(options: Mapping[str, Any]) -> list[CommandSpec]:
    """The vocabulary of a vehicle with these ``adapter_options`` (ValueError on a bad one)."""
    return mavlink_vocabulary(MavlinkConfig.from_options(options))
