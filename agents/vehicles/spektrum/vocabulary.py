"""What the plane offers users: two virtual sticks, the flight mode, arming, landing.

Light on purpose (no pyserial): the platform reads the vocabulary from a config through
the integration (:func:`spektrum_commands`), as the adapter declares it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from agents.vehicles.base import CommandSpec
from agents.vehicles.spektrum.config import SpektrumConfig

#: stick command -> (axis, sign). The keys mirror the physical right stick: ArrowUp
#: pushes it forward (nose down: forward flight in VTOL mode, a dive in aircraft mode).
STICK_COMMANDS: dict[str, tuple[str, float]] = {
    "yaw_left": ("rudder", -1.0),
    "yaw_right": ("rudder", 1.0),
    "pitch_up": ("elevator", 1.0),
    "pitch_down": ("elevator", -1.0),
    "roll_left": ("aileron", -1.0),
    "roll_right": ("aileron", 1.0),
}

TELEMETRY_TOPICS = [
    "altitude",
    "speed",
    "heading",
    "flight_mode",
    "is_armed",
    "throttle",
    "channels",
    "frame_period_ms",
    "battery_level",
    "location",
    "landing",
]


def spektrum_vocabulary(config: SpektrumConfig) -> list[CommandSpec]:
    """Stick, mode and set-up commands; see docs/vehicles/vtol.md for the mapping."""
    cfg = config
    step = {
        "step": {
            "type": "number",
            "min": 0.01,
            "max": 0.25,
            "default": cfg.throttle_step,
            "description": "throttle change per command, fraction of full",
        }
    }
    amount = {
        "amount": {
            "type": "number",
            "min": 0.05,
            "max": 1,
            "default": cfg.stick_deflection,
            "description": "stick deflection while held, fraction of full",
        }
    }
    out = [
        CommandSpec(
            "throttle_up",
            "More throttle (climb; in aircraft mode: faster)",
            group="left_stick",
            args=step,
            motion=True,
            speed_arg="step",
            key="w",
        ),
        CommandSpec(
            "throttle_down",
            "Less throttle (descend; in aircraft mode: slower)",
            group="left_stick",
            args=step,
            motion=True,
            key="s",
        ),
        CommandSpec(
            "yaw_left",
            "Yaw left (rudder) while held",
            group="left_stick",
            args=amount,
            motion=True,
            speed_arg="amount",
            key="a",
        ),
        CommandSpec(
            "yaw_right",
            "Yaw right (rudder) while held",
            group="left_stick",
            args=amount,
            motion=True,
            speed_arg="amount",
            key="d",
        ),
        CommandSpec(
            "pitch_down",
            "Stick forward: fly forward (aircraft mode: dive)",
            group="right_stick",
            args=amount,
            motion=True,
            speed_arg="amount",
            key="ArrowUp",
        ),
        CommandSpec(
            "pitch_up",
            "Stick back: fly backward (aircraft mode: climb)",
            group="right_stick",
            args=amount,
            motion=True,
            speed_arg="amount",
            key="ArrowDown",
        ),
        CommandSpec(
            "roll_left",
            "Roll left: slide left (aircraft mode: bank and turn)",
            group="right_stick",
            args=amount,
            motion=True,
            speed_arg="amount",
            key="ArrowLeft",
        ),
        CommandSpec(
            "roll_right",
            "Roll right: slide right (aircraft mode: bank and turn)",
            group="right_stick",
            args=amount,
            motion=True,
            speed_arg="amount",
            key="ArrowRight",
        ),
        CommandSpec(
            "change_to_vtol_mode", "Rotors up: hover like a multicopter", group="mode", key="v"
        ),
        CommandSpec(
            "change_to_aircraft_mode",
            f"Rotors forward: fly like a plane (from {cfg.min_transition_altitude_m:g} m up)",
            group="mode",
            key="p",
        ),
        # No default keys: arming must not be a stray keystroke.
        CommandSpec("arm", "Arm the motors (throttle must be at idle)", group="setup"),
        CommandSpec("disarm", "Disarm the motors (on the ground only)", group="setup"),
        CommandSpec("land", "Land where it is, then disarm", group="setup", key="l"),
        # Sent by the browser when the last held key goes up.
        CommandSpec(
            "stop",
            "Sticks and throttle to neutral: hover (VTOL mode) or level cruise",
            group="setup",
            key="Space",
        ),
    ]
    return out


def spektrum_commands(options: Mapping[str, Any]) -> list[CommandSpec]:
    """The vocabulary of a plane with these ``adapter_options`` (ValueError on a bad one)."""
    return spektrum_vocabulary(SpektrumConfig.from_options(options))
