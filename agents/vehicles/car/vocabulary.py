"""What a car offers users: its commands and telemetry topics.

Light on purpose (no gpiozero): the platform reads a car's vocabulary from its options
through the integration (:func:`car_commands`), as the adapter declares it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from agents.vehicles.base import CommandSpec
from agents.vehicles.car.config import CarConfig

SPEED_ARG = {
    "speed": {
        "type": "number",
        "min": 0,
        "max": 1,
        "default": 0.5,
        "description": "fraction of full motor power",
    }
}
STEP_ARG = {"step_deg": {"type": "number", "min": 1, "max": 90, "default": 10, "unit": "deg"}}

#: The movement commands, as (name, description, key binding).
MOVES = (
    ("forward", "Drive forwards (refused when an obstacle is close ahead)", "ArrowUp"),
    ("backward", "Drive backwards", "ArrowDown"),
)
#: Turning on the spot, slower by default (:attr:`CarConfig.turn_power`): a held key at
#: the driving speed spun the car several turns a second, too fast to aim.
TURNS = (
    ("left", "Turn left on the spot", "ArrowLeft"),
    ("right", "Turn right on the spot", "ArrowRight"),
)
#: The camera arm's commands (with ``camera_arm``), as (name, description, key binding).
CAMERA_MOVES = (
    ("camera_up", "Tilt the camera up", "w"),
    ("camera_down", "Tilt the camera down", "s"),
    ("camera_left", "Pan the camera left", "a"),
    ("camera_right", "Pan the camera right", "d"),
)

TELEMETRY_TOPICS = [
    "battery_level",
    "location",
    "heading",
    "speed",
    "distance_ahead",
    "camera_pan",
    "camera_tilt",
    "motors",
]


def car_vocabulary(config: CarConfig) -> list[CommandSpec]:
    """Driving commands, plus the camera arm's when ``camera_arm`` is set."""
    turn_arg = {
        "speed": {
            **SPEED_ARG["speed"],
            "default": config.turn_power,
            "description": f"fraction of full motor power (default: about "
            f"{config.turn_rate_deg_s:g}°/s on the spot)",
        }
    }
    out = [
        CommandSpec(
            name,
            text,
            group="movement",
            args=args,
            motion=True,
            speed_arg="speed",
            key=key,
        )
        for moves, args in ((MOVES, SPEED_ARG), (TURNS, turn_arg))
        for name, text, key in moves
    ]
    # Not a motion command: it moves nothing, and must pass every limit anyway.
    out.append(CommandSpec("stop", "Stop the motors", group="movement", key="Space"))
    if config.camera_arm:
        for name, text, key in CAMERA_MOVES:
            out.append(CommandSpec(name, text, group="camera", args=STEP_ARG, key=key))
        out.append(CommandSpec("camera_center", "Centre the camera", group="camera", key="c"))
    return out


def car_commands(options: Mapping[str, Any]) -> list[CommandSpec]:
    """The vocabulary of a car with these ``adapter_options`` (ValueError on a bad one)."""
    return car_vocabulary(CarConfig.from_options(options))
