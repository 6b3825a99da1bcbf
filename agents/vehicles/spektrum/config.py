"""The Spektrum plane's options (``adapter_options``), checked.

Read with the kit's :class:`~agents.vehicles.kit.OptionReader` (unknown keys refused);
each option is described in ``docs/vehicles/vtol.md``. No pyserial here: the platform
reads the vocabulary from a config without it.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from agents.vehicles.kit import OptionReader
from agents.vehicles.spektrum.frames import AUX1, CHANNEL_NAMES, GEAR, PROTOCOLS, SWITCH_CHANNELS

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SpektrumConfig:
    """The adapter's options, checked. See ``docs/vehicles/vtol.md`` for each one."""

    writer: str = "auto"  # "process" (the frame pump), "thread"; auto: process if it can
    pump_realtime: bool = True
    pump_stale_s: float = 1.0
    port: str = "/dev/serial0"
    baudrate: int = 115200
    protocol: str = "dsmx_2048"
    frame_period_ms: float = 11.0
    write_timeout_ms: float = 50.0
    # sticks
    throttle_step: float = 0.05
    stick_deflection: float = 0.5
    stick_hold_ms: float = 250.0
    stick_hold_max_ms: float = 1000.0
    arm_max_throttle: float = 0.05
    mode_channel: int = GEAR
    arm_channel: int = AUX1
    reversed_channels: frozenset[int] = frozenset()
    # flight envelope, shared with the simulator's model
    min_transition_altitude_m: float = 20.0
    allow_transition_without_altitude: bool = False
    hover_throttle: float = 0.5
    cruise_throttle: float = 0.6
    max_climb_mps: float = 4.0
    max_descent_mps: float = 4.0
    vtol_max_speed_mps: float = 6.0
    aircraft_climb_mps: float = 5.0
    transition_s: float = 3.0
    # landing and watchdogs
    land_throttle: float = 0.35
    land_ramp_per_s: float = 0.25
    land_timeout_s: float = 60.0
    loop_watchdog_s: float = 2.0
    telemetry_stale_s: float = 1.0
    close_timeout_s: float = 30.0
    #: Where the plane takes off from (its home), if known.
    origin: tuple[float, float] | None = None

    @property
    def system(self) -> int:
        return PROTOCOLS[self.protocol][0]

    @property
    def period_s(self) -> float:
        return self.frame_period_ms / 1000.0

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> SpektrumConfig:
        """Check ``options``; raises ValueError naming the first bad one (or every
        unknown key)."""
        o = OptionReader("spektrum", options)
        protocol = o.choice("protocol", "dsmx_2048", sorted(PROTOCOLS))
        nominal = PROTOCOLS[protocol][1]
        period = o.number("frame_period_ms", nominal, min=5.0, max=50.0)
        if abs(period - nominal) > 0.2 * nominal:
            logger.warning(
                "spektrum: frame_period_ms %g differs from %s's nominal %g ms",
                period,
                protocol,
                nominal,
            )
        mode_channel = CHANNEL_NAMES.index(o.choice("mode_channel", "gear", SWITCH_CHANNELS))
        arm_channel = CHANNEL_NAMES.index(o.choice("arm_channel", "aux1", SWITCH_CHANNELS))
        if mode_channel == arm_channel:
            raise ValueError("spektrum options mode_channel and arm_channel must differ")
        reversed_names = o.names("reversed_channels", CHANNEL_NAMES)
        hold = o.number("stick_hold_ms", 250.0, min=20.0, max=5000.0)
        hold_max = o.number("stick_hold_max_ms", 1000.0, min=20.0, max=5000.0)
        if hold_max < hold:
            raise o.error("stick_hold_max_ms", "must be >= stick_hold_ms")
        hover = o.number("hover_throttle", 0.5, min=0.05, max=0.95)
        land = o.number("land_throttle", 0.35, min=0.0, max=1.0)
        if land >= hover:
            raise o.error("land_throttle", "must be below hover_throttle")
        config = cls(
            writer=o.choice("writer", "auto", ("auto", "thread", "process")),
            pump_realtime=o.flag("pump_realtime", True),
            pump_stale_s=o.number("pump_stale_s", 1.0, min=0.05, max=10.0),
            port=o.text("port", "/dev/serial0", what="a device path or pyserial URL"),
            baudrate=o.integer("baudrate", 115200, min=1),
            protocol=protocol,
            frame_period_ms=period,
            write_timeout_ms=o.number("write_timeout_ms", 50.0, above=0.0),
            throttle_step=o.number("throttle_step", 0.05, above=0.0, max=1.0),
            stick_deflection=o.number("stick_deflection", 0.5, above=0.0, max=1.0),
            stick_hold_ms=hold,
            stick_hold_max_ms=hold_max,
            arm_max_throttle=o.number("arm_max_throttle", 0.05, min=0.0, max=0.3),
            mode_channel=mode_channel,
            arm_channel=arm_channel,
            reversed_channels=frozenset(CHANNEL_NAMES.index(n) for n in reversed_names),
            min_transition_altitude_m=o.number("min_transition_altitude_m", 20.0, min=0.0),
            allow_transition_without_altitude=o.flag("allow_transition_without_altitude"),
            hover_throttle=hover,
            cruise_throttle=o.number("cruise_throttle", 0.6, above=0.0, max=1.0),
            max_climb_mps=o.number("max_climb_mps", 4.0, above=0.0),
            max_descent_mps=o.number("max_descent_mps", 4.0, above=0.0),
            vtol_max_speed_mps=o.number("vtol_max_speed_mps", 6.0, above=0.0),
            aircraft_climb_mps=o.number("aircraft_climb_mps", 5.0, above=0.0),
            transition_s=o.number("transition_s", 3.0, min=0.0, max=30.0),
            land_throttle=land,
            land_ramp_per_s=o.number("land_ramp_per_s", 0.25, above=0.0),
            land_timeout_s=o.number("land_timeout_s", 60.0, above=0.0),
            loop_watchdog_s=o.number("loop_watchdog_s", 2.0, min=0.0),
            telemetry_stale_s=o.number("telemetry_stale_s", 1.0, above=0.0),
            close_timeout_s=o.number("close_timeout_s", 30.0, min=0.0),
            origin=o.origin(),
        )
        o.finish()
        return config

    def model_params(self) -> dict[str, float]:
        """The flight envelope the simulator's model shares with the adapter (so that
        projections and landings agree with the model), as model parameters."""
        return {
            "hover_throttle": self.hover_throttle,
            "max_climb_mps": self.max_climb_mps,
            "max_descent_mps": self.max_descent_mps,
            "vtol_max_speed_mps": self.vtol_max_speed_mps,
            "aircraft_climb_mps": self.aircraft_climb_mps,
            "transition_s": self.transition_s,
            "failsafe_throttle": self.land_throttle,
        }
