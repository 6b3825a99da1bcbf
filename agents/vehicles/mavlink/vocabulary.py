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
from agents.vehicles.mavlink.classes import VehicleClass
from agents.vehicles.mavlink.config import MavlinkConfig

#: A copter's telemetry topics.
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


#: A rover's or a boat's: no altitude, a driving ``mode``.
ROVER_TELEMETRY_TOPICS = [
    "battery_level",
    "location",
    "speed",
    "heading",
    "mode",
    "is_armed",
    "number_of_gps_satellites",
    "autopilot_link",
    "gps_fix",
    "ekf_ok",
]


def rover_vocabulary(config: MavlinkConfig) -> list[CommandSpec]:
    """A rover's or a boat's commands: drive with the arrows (forward and backward at a
    speed, left and right at a turn rate; together, a curve), stop, go home, go to a
    position, and drop the payload if it has one."""
    what = config.vehicle_class.name
    speed = {
        "speed_mps": {
            "type": "number",
            "min": 0.1,
            "max": config.max_speed_mps,
            "default": config.move_speed_mps,
            "unit": "m/s",
        }
    }
    rate = {
        "rate_deg_s": {
            "type": "number",
            "min": 1,
            "max": config.max_turn_rate_deg_s,
            "default": config.turn_rate_deg_s,
            "unit": "deg/s",
        }
    }

    def move(name: str, text: str, args: Any, speed_arg: str, key: str) -> CommandSpec:
        return CommandSpec(
            name, text, group="movement", args=args, motion=True, speed_arg=speed_arg, key=key
        )

    return [
        CommandSpec("arm", "Arm the motors (in GUIDED)", group="setup"),
        CommandSpec("disarm", f"Disarm the motors (the {what} stopped)", group="setup"),
        move("forward", "Go forward", speed, "speed_mps", "ArrowUp"),
        move("backward", "Go backward", speed, "speed_mps", "ArrowDown"),
        move(
            "left",
            "Turn left (on the spot, or in a curve while going)",
            rate,
            "rate_deg_s",
            "ArrowLeft",
        ),
        move(
            "right",
            "Turn right (on the spot, or in a curve while going)",
            rate,
            "rate_deg_s",
            "ArrowRight",
        ),
        # Not a motion command: it moves nothing, and must pass every limit anyway.
        CommandSpec("stop", "Stop", group="movement", key="Space"),
        CommandSpec(
            "return_to_home", "Go back to the launch point and hold there", group="mission", key="h"
        ),
        *(
            [CommandSpec("release_payload", "Drop the payload", group="mission", key="r")]
            if config.payload is not None
            else []
        ),
        CommandSpec(
            "go_to_waypoint",
            "Go to a position",
            group="mission",
            args={
                "lat": {"type": "number", "min": -90, "max": 90, "unit": "deg"},
                "lon": {"type": "number", "min": -180, "max": 180, "unit": "deg"},
                # 0: the autopilot's own cruise speed (WP_SPEED, else CRUISE_SPEED).
                "speed_mps": {
                    "type": "number",
                    "min": 0,
                    "max": config.max_speed_mps,
                    "default": 0,
                    "unit": "m/s",
                },
            },
        ),
    ]


def mavlink_vocabulary(config: MavlinkConfig) -> list[CommandSpec]:
    """The commands of the vehicle class ``config`` names."""
    if config.vehicle_class.flies:
        return copter_vocabulary(config)
    return rover_vocabulary(config)


def telemetry_topics(vehicle_class: VehicleClass) -> list[str]:
    """The telemetry topics of ``vehicle_class``."""
    return list(TELEMETRY_TOPICS if vehicle_class.flies else ROVER_TELEMETRY_TOPICS)


def mavlink_commands(options: Mapping[str, Any]) -> list[CommandSpec]:
    """The vocabulary of a vehicle with these ``adapter_options`` (ValueError on a bad one)."""
    return mavlink_vocabulary(MavlinkConfig.from_options(options))
