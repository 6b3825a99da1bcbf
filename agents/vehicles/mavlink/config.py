"""The MAVLink adapter's options (``adapter_options``), checked.

Read with the kit's :class:`~agents.vehicles.kit.OptionReader`: unknown keys are refused,
and so are the options of another vehicle class (``take_off`` heights on a boat). Each
option is described in ``docs/vehicles/quadcopter.md`` (copter) and
``docs/vehicles/boat.md`` (boat, rover). No pymavlink here: the platform reads the
vocabulary from a config without it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from agents.vehicles.kit import OptionReader
from agents.vehicles.mavlink.classes import COPTER, VEHICLE_CLASSES, VehicleClass

#: Velocity frames the ``velocity_frame`` option accepts (a copter's body frame).
VELOCITY_FRAMES = {
    "body_offset_ned": 9,  # MAV_FRAME_BODY_OFFSET_NED: ArduCopter rotates by heading
    "body_ned": 8,  # MAV_FRAME_BODY_NED: the same in ArduCopter, body velocity in PX4
    "body_frd": 12,  # MAV_FRAME_BODY_FRD: newer firmware only
}

#: Telemetry streams asked for with MAV_CMD_SET_MESSAGE_INTERVAL, in Hz.
DEFAULT_STREAM_RATES_HZ: dict[str, float] = {
    "GLOBAL_POSITION_INT": 10.0,
    "ATTITUDE": 10.0,
    "VFR_HUD": 4.0,
    "SYS_STATUS": 2.0,
    "GPS_RAW_INT": 2.0,
    "EXTENDED_SYS_STATE": 2.0,
    "BATTERY_STATUS": 1.0,
    "EKF_STATUS_REPORT": 1.0,
    "HOME_POSITION": 0.5,
    # Where the autopilot is in a native mission (ArduPilot also sends it on a change).
    "MISSION_CURRENT": 2.0,
}

#: What ``close_action`` may be.
CLOSE_ACTIONS = ("return_to_home", "land", "stop", "none")


@dataclass(frozen=True)
class MavlinkConfig:
    """The adapter's options, checked. ``vehicle_class`` is a
    :class:`~agents.vehicles.mavlink.classes.VehicleClass`; the copter's options
    (take-off, rotation, velocity frame) keep their defaults on a rover or a boat, and
    a boat's (turn rate) on a copter."""

    connection: str = "udpin:0.0.0.0:14550"
    vehicle_class: VehicleClass = COPTER
    origin: tuple[float, float] | None = None
    source_system: int = 255
    source_component: int = 190  # MAV_COMP_ID_MISSIONPLANNER: a GCS
    target_system: int | None = None
    target_component: int | None = None
    baud: int = 57600
    command_timeout_s: float = 3.0
    resend_s: float = 1.0
    heartbeat_timeout_s: float = 3.0
    connect_timeout_s: float = 10.0
    low_battery_pct: float = 25.0
    move_speed_mps: float = 1.0
    max_speed_mps: float = 10.0
    setpoint_hold_s: float = 1.0
    #: The deceleration the vehicle brakes at (m/s²; a copter's horizontal one), and a
    #: copter's vertical one; None: read from the autopilot (see :mod:`.braking`).
    decel_mps2: float | None = None
    decel_z_mps2: float | None = None
    stream_rates_hz: Mapping[str, float] = field(
        default_factory=lambda: dict(DEFAULT_STREAM_RATES_HZ)
    )
    close_action: str = "return_to_home"
    #: How a payload is dropped, if the vehicle carries one: {"method": "gripper"} or
    #: {"method": "servo", "servo": 9, "pwm": 1900}; None: no ``release_payload``.
    payload: Mapping[str, Any] | None = None
    #: Hand a mission of plain waypoints and actions to the autopilot's AUTO (see
    #: :meth:`~.adapter.MavlinkAdapter.native_missions`); False: fly it step by step.
    native_missions: bool = True
    # copter
    takeoff_default_m: float = 5.0
    max_takeoff_m: float = 120.0
    rotate_default_deg: float = 15.0
    rotate_rate_deg_s: float = 45.0
    velocity_frame: str = "body_offset_ned"
    # rover, boat
    turn_rate_deg_s: float = 30.0
    max_turn_rate_deg_s: float = 90.0

    @property
    def flies(self) -> bool:
        return self.vehicle_class.flies

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> MavlinkConfig:
        """Check ``options``; raises ValueError naming the first bad one (or every
        unknown key)."""
        o = OptionReader("mavlink", options)
        vehicle_class = VEHICLE_CLASSES[o.choice("vehicle_class", "copter", VEHICLE_CLASSES)]
        source = o.optional_integer("source_system", min=0, max=255)
        component = o.optional_integer("source_component", min=0, max=255)
        rates = dict(DEFAULT_STREAM_RATES_HZ)
        custom = o.mapping("stream_rates_hz")
        streams = OptionReader("mavlink", custom, prefix="stream_rates_hz.")
        for name in custom:
            if name not in DEFAULT_STREAM_RATES_HZ:
                raise o.error("stream_rates_hz", f"unknown message {name}")
            rates[name] = streams.number(name, 1.0, above=0, max=50)
        payload = o.get("payload")
        if payload is not None:
            _check_payload(o, payload)
        common: dict[str, Any] = {
            "connection": o.text(
                "connection", "udpin:0.0.0.0:14550", what="a pymavlink connection string"
            ),
            "vehicle_class": vehicle_class,
            "origin": o.origin(),
            "source_system": 255 if source is None else source,
            "source_component": component or 190,
            "target_system": o.optional_integer("target_system", min=0, max=255),
            "target_component": o.optional_integer("target_component", min=0, max=255),
            "baud": o.integer("baud", 57600, min=1),
            "command_timeout_s": o.number("command_timeout_s", 3.0, above=0, max=60),
            "resend_s": o.number("resend_s", 1.0, above=0, max=60),
            "heartbeat_timeout_s": o.number("heartbeat_timeout_s", 3.0, above=0, max=60),
            "connect_timeout_s": o.number("connect_timeout_s", 10.0, above=0, max=600),
            "low_battery_pct": o.number("low_battery_pct", 25.0, min=0, max=100),
            "move_speed_mps": o.number("move_speed_mps", 1.0, above=0, max=50),
            "max_speed_mps": o.number("max_speed_mps", 10.0, above=0, max=50),
            "setpoint_hold_s": o.number("setpoint_hold_s", 1.0, above=0, max=3.0),
            "decel_mps2": o.optional_number("decel_mps2", above=0, max=50),
            "stream_rates_hz": rates,
            "close_action": o.choice("close_action", "return_to_home", CLOSE_ACTIONS),
            "payload": None if payload is None else dict(payload),
            "native_missions": o.flag("native_missions", True),
        }
        if vehicle_class.flies:
            specific: dict[str, Any] = {
                "takeoff_default_m": o.number("takeoff_default_m", 5.0, above=0, max=1000),
                "max_takeoff_m": o.number("max_takeoff_m", 120.0, above=0, max=1000),
                "rotate_default_deg": o.number("rotate_default_deg", 15.0, above=0, max=180),
                "rotate_rate_deg_s": o.number("rotate_rate_deg_s", 45.0, above=0, max=360),
                "velocity_frame": o.choice("velocity_frame", "body_offset_ned", VELOCITY_FRAMES),
                "decel_z_mps2": o.optional_number("decel_z_mps2", above=0, max=50),
            }
        else:
            specific = {
                "turn_rate_deg_s": o.number("turn_rate_deg_s", 30.0, above=0, max=360),
                "max_turn_rate_deg_s": o.number("max_turn_rate_deg_s", 90.0, above=0, max=360),
            }
        o.finish()
        config = cls(**common, **specific)
        if config.takeoff_default_m > config.max_takeoff_m:
            raise o.error("takeoff_default_m", "above max_takeoff_m")
        if config.move_speed_mps > config.max_speed_mps:
            raise o.error("move_speed_mps", "above max_speed_mps")
        if config.turn_rate_deg_s > config.max_turn_rate_deg_s:
            raise o.error("turn_rate_deg_s", "above max_turn_rate_deg_s")
        if config.close_action == "land" and not vehicle_class.flies:
            raise o.error("close_action", f"a {vehicle_class.name} cannot land")
        return config


def _check_payload(o: OptionReader, payload: Any) -> None:
    if not isinstance(payload, Mapping) or payload.get("method") not in ("gripper", "servo"):
        raise o.error("payload", '{"method": "gripper"} or "servo"')
    p = OptionReader("mavlink", payload, prefix="payload.")
    p.get("method")
    if payload["method"] == "servo":
        p.integer("servo", 0, min=1, max=32)
        p.integer("pwm", 0, min=800, max=2200)
    p.finish()
