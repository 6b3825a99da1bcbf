"""Adapter for the paper's Spektrum VTOL plane (section 4.2.3), over a serial port.

The E-flite Convergence VTOL has a closed flight controller (FC) that expects a Spektrum
remote receiver on its receiver port. The paper replaced that receiver with a
microcontroller writing Spektrum frames; this adapter does the same job from the agent's
computer through a UART (pyserial), so users fly the plane with two virtual sticks.

Wire format: **DSMX 2048, 11 ms** ("remote receiver" serial format, Spektrum's
*Specification for Spektrum Remote Receiver Interfacing*; see ``docs/vehicles/vtol.md``
for the layout and sources). We chose it over SRXL2 because it is what the paper
describes (a unidirectional line from receiver to FC), it needs no handshake, device
IDs or CRC negotiation with a closed FC that we cannot inspect, and every FC that
takes a Spektrum satellite decodes it. 115200 baud 8N1; every ``frame_period_ms`` one
16-byte frame::

    byte 0      fades (lost-frame counter of a real receiver; always 0 here)
    byte 1      system: 0xB2 = DSMX 11 ms 2048, 0xA2 = DSMX 22 ms 2048
    bytes 2..15 seven big-endian servo words:
                bit 15      phase: set in the first word of the second frame of a pair
                bits 14..11 channel id (0 throttle, 1 aileron, 2 elevator, 3 rudder,
                            4 gear, 5 aux1, 6 aux2, 7 aux3)
                bits 10..0  servo position 0..2047 (centre 1024; 342..1706 = 100 %
                            travel = about 1100..1900 us)

Eight channels do not fit seven slots, so frames alternate: A carries channels 0..6, B
(phase bit set) channels 0..5 and 7. Sticks, mode and arm switch therefore go out in
every frame; aux2/aux3 (unused, centred) every other one.

Timing (why neither the asyncio loop nor a thread): the FC wants a frame every 11 ms
whatever the network, the event loop or the video encoder is doing. A Python thread
shares the interpreter lock with the event loop, and with a CPU-heavy coroutine on the
loop its wake-ups came 5-50 ms late (measured: mean period 16-19 ms). So, like the
paper's dedicated microcontroller, a small **frame pump process** owns the schedule:
it sleeps until deadlines on a fixed monotonic grid (lateness never accumulates),
writes each frame to the port's file descriptor, runs with real-time priority when
permitted, and stops sending (a receiver loss for the FC) if the agent stops feeding
it. In the agent, a control thread ticks the virtual sticks every 10 ms (hold timeouts,
the landing sequence, a watchdog on the event loop) and sends the servo positions to
the pump; a reader thread takes what comes back on the line. The event loop only
changes the stick state under a lock. Ports without a file descriptor (pyserial URLs
such as ``loop://``) fall back to a writer thread.

Telemetry: the Convergence's FC sends nothing back over the receiver line, so on the
real plane altitude, speed, position and battery are unknown (``None``) unless a
companion sensor writes the same JSON lines as the simulator onto the return line. In
simulation (``simulate``), :mod:`agents.vehicles.spektrum.sim.simulator` sits on the other
end of a pty, decodes the frames, checks their framing and timing, flies a VTOL/airplane model and
reports its state back as JSON lines. Anything malformed on the return line is counted
and ignored.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import itertools
import json
import logging
import math
import os
import struct
import subprocess
import sys
import threading
import time
import tty
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

# pyserial ships no type hints of its own (types-pyserial adds them when installed).
import serial  # type: ignore[import-untyped, unused-ignore]

from agents.geo import local_offset_m, offset
from agents.vehicles.base import (
    Adapter,
    AdapterError,
    Breach,
    CommandSpec,
    Projection,
    VehicleState,
)
from agents.vehicles.kit import OptionReader

logger = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------
# Wire format
# --------------------------------------------------------------------------------------

FRAME_SIZE = 16
SERVOS_PER_FRAME = 7
#: Value of an unused servo slot (decoders skip it).
EMPTY_SLOT = 0xFFFF
PHASE_BIT = 0x8000
CHANNEL_ID_MASK = 0x7800
CHANNEL_ID_SHIFT = 11
SERVO_MASK = 0x07FF

SYSTEM_DSMX_22MS = 0xA2
SYSTEM_DSMX_11MS = 0xB2
#: protocol option -> (system byte, nominal frame period in ms)
PROTOCOLS: dict[str, tuple[int, float]] = {
    "dsmx_2048": (SYSTEM_DSMX_11MS, 11.0),
    "dsmx_2048_22ms": (SYSTEM_DSMX_22MS, 22.0),
}

#: 2048 mode: positions 0..2047 (the spec's 150 % travel, about 903..2097 us).
SERVO_MIN = 0
SERVO_MAX = 2047
SERVO_CENTRE = 1024
#: 100 % stick travel (about +-400 us around 1500 us): everything we send stays inside.
SERVO_TRAVEL = 682
SERVO_LOW = SERVO_CENTRE - SERVO_TRAVEL  # 342
SERVO_HIGH = SERVO_CENTRE + SERVO_TRAVEL  # 1706

# Spektrum channel order.
THROTTLE, AILERON, ELEVATOR, RUDDER, GEAR, AUX1, AUX2, AUX3 = range(8)
CHANNEL_NAMES = ("throttle", "aileron", "elevator", "rudder", "gear", "aux1", "aux2", "aux3")
CHANNEL_COUNT = len(CHANNEL_NAMES)
SWITCH_CHANNELS = ("gear", "aux1", "aux2", "aux3")
#: Channels of the two alternating frames (A: phase 0, B: phase 1).
FRAME_A_CHANNELS = (THROTTLE, AILERON, ELEVATOR, RUDDER, GEAR, AUX1, AUX2)
FRAME_B_CHANNELS = (THROTTLE, AILERON, ELEVATOR, RUDDER, GEAR, AUX1, AUX3)

#: The stick axes that centre themselves, by channel.
STICK_AXES = {"aileron": AILERON, "elevator": ELEVATOR, "rudder": RUDDER}


class FrameError(ValueError):
    """A 16-byte block is not a valid frame; ``reason`` is a short machine word."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class DecodedFrame:
    """One decoded frame: header bytes, phase bit and channel id -> servo position."""

    fades: int
    system: int
    phase: bool
    servos: dict[int, int]


def encode_frame(
    servos: Sequence[tuple[int, int]], *, phase: bool, system: int, fades: int = 0
) -> bytes:
    """Build one 16-byte frame from up to seven (channel id, servo position) pairs.

    Unused slots are filled with 0xFFFF. The phase bit goes into the first word when
    ``phase``. Raises ValueError for more than seven servos, a channel id outside
    0..15 or a position outside 0..2047 (callers clamp first: this is the last line of
    defence, not the clamp).
    """
    if len(servos) > SERVOS_PER_FRAME:
        raise ValueError("a frame holds at most seven servo words")
    out = bytearray((fades & 0xFF, system & 0xFF))
    for i, (channel, position) in enumerate(servos):
        if not 0 <= channel <= 15:
            raise ValueError(f"channel id {channel} out of range")
        if not SERVO_MIN <= position <= SERVO_MAX:
            raise ValueError(f"servo position {position} out of range")
        word = (channel << CHANNEL_ID_SHIFT) | position
        if phase and i == 0:
            word |= PHASE_BIT
        out += word.to_bytes(2, "big")
    while len(out) < FRAME_SIZE:
        out += EMPTY_SLOT.to_bytes(2, "big")
    return bytes(out)


def decode_frame(frame: bytes, *, max_channel: int = CHANNEL_COUNT - 1) -> DecodedFrame:
    """Decode a 16-byte 2048-mode frame.

    Raises FrameError: ``size`` (not 16 bytes), ``channel_id`` (an id above
    ``max_channel``), ``duplicate`` (a channel twice in one frame), ``empty`` (no
    servo word at all). The system byte is returned, not checked (the caller knows what
    it expects).
    """
    if len(frame) != FRAME_SIZE:
        raise FrameError("size", f"a frame is {FRAME_SIZE} bytes, got {len(frame)}")
    servos: dict[int, int] = {}
    phase = False
    for i in range(SERVOS_PER_FRAME):
        word = int.from_bytes(frame[2 + 2 * i : 4 + 2 * i], "big")
        if word == EMPTY_SLOT:
            continue
        if i == 0:
            phase = bool(word & PHASE_BIT)
        channel = (word & CHANNEL_ID_MASK) >> CHANNEL_ID_SHIFT
        if channel > max_channel:
            raise FrameError("channel_id", f"channel id {channel} in slot {i}")
        if channel in servos:
            raise FrameError("duplicate", f"channel {channel} twice in one frame")
        servos[channel] = word & SERVO_MASK
    if not servos:
        raise FrameError("empty", "no servo word in the frame")
    return DecodedFrame(fades=frame[0], system=frame[1], phase=phase, servos=servos)


def clamp_servo(position: float) -> int:
    """``position`` rounded and clamped to 100 % travel (342..1706)."""
    if not math.isfinite(position):
        return SERVO_CENTRE  # a NaN must not fly
    return max(SERVO_LOW, min(SERVO_HIGH, round(position)))


def stick_to_servo(value: float) -> int:
    """A centred stick in -1..1 (clamped) to a servo position (-1 342, 0 1024, 1 1706);
    a non-finite value (never produced by our commands) centres the stick."""
    if not math.isfinite(value):
        return SERVO_CENTRE
    return clamp_servo(SERVO_CENTRE + max(-1.0, min(1.0, value)) * SERVO_TRAVEL)


def throttle_to_servo(value: float) -> int:
    """Throttle 0..1 (clamped) to a servo position (0 342, 1 1706); a non-finite
    value gives idle."""
    if not math.isfinite(value):
        return SERVO_LOW
    return clamp_servo(SERVO_LOW + max(0.0, min(1.0, value)) * 2 * SERVO_TRAVEL)


def servo_to_stick(position: int) -> float:
    """Inverse of :func:`stick_to_servo`, clamped to -1..1."""
    return max(-1.0, min(1.0, (position - SERVO_CENTRE) / SERVO_TRAVEL))


def servo_to_throttle(position: int) -> float:
    """Inverse of :func:`throttle_to_servo`, clamped to 0..1."""
    return max(0.0, min(1.0, (position - SERVO_LOW) / (2 * SERVO_TRAVEL)))


# --------------------------------------------------------------------------------------
# The return line: JSON lines from the simulator (or a companion sensor)
# --------------------------------------------------------------------------------------

#: Longest return line accepted; longer ones are dropped (and counted) whole.
MAX_RETURN_LINE = 2048

_NUMBER_FIELDS = (
    "alt",
    "vz",
    "speed",
    "airspeed",
    "heading",
    "lat",
    "lon",
    "battery",
    "period_ms",
    "jitter_ms",
    "max_gap_ms",
)
_BOOL_FIELDS = ("armed", "on_ground", "stalled", "crashed", "fc_failsafe")
_INT_FIELDS = (
    "frames",
    "bad_frames",
    "hard_landings",
    "arm_refused",
    "out_of_travel",
    "close_frames",
)
FC_MODES = ("vtol", "transition", "aircraft")


@dataclass(frozen=True)
class FcReport:
    """One state report from the far end of the line; None where not reported.

    ``mode`` is "vtol", "transition" or "aircraft"; ``alt`` metres above the take-off
    point; ``speed`` horizontal ground speed and ``airspeed`` forward speed in m/s;
    ``heading`` degrees clockwise from north; ``battery`` percent; ``period_ms``,
    ``jitter_ms`` (p99 of |period - nominal|) and ``max_gap_ms`` the frame timing as
    the receiving end measured it.
    """

    alt: float | None = None
    vz: float | None = None
    speed: float | None = None
    airspeed: float | None = None
    heading: float | None = None
    lat: float | None = None
    lon: float | None = None
    battery: float | None = None
    period_ms: float | None = None
    jitter_ms: float | None = None
    max_gap_ms: float | None = None
    armed: bool | None = None
    on_ground: bool | None = None
    stalled: bool | None = None
    crashed: bool | None = None
    fc_failsafe: bool | None = None
    frames: int | None = None
    bad_frames: int | None = None
    hard_landings: int | None = None
    arm_refused: int | None = None
    out_of_travel: int | None = None
    close_frames: int | None = None
    mode: str | None = None
    bad_reasons: Mapping[str, int] | None = None


def parse_report(line: bytes) -> FcReport:
    """Parse one return line (without its newline). Raises ValueError when it is not a
    JSON object or a known field has the wrong type or an impossible value; unknown
    fields are ignored (a newer simulator may report more)."""
    data = json.loads(line)  # bytes: JSON detects UTF-8/16/32 itself
    if not isinstance(data, dict):
        raise ValueError("a report is a JSON object")
    values: dict[str, Any] = {}
    for name in _NUMBER_FIELDS:
        value = data.get(name)
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{name} must be a number")
        if not math.isfinite(value):
            raise ValueError(f"{name} must be finite")
        values[name] = float(value)
    for name in _BOOL_FIELDS:
        value = data.get(name)
        if value is None:
            continue
        if not isinstance(value, bool):
            raise ValueError(f"{name} must be true or false")
        values[name] = value
    for name in _INT_FIELDS:
        value = data.get(name)
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{name} must be a count")
        values[name] = value
    reasons = data.get("bad_reasons")
    if reasons is not None:
        if not isinstance(reasons, dict) or len(reasons) > 32:
            raise ValueError("bad_reasons must be a small object of counts")
        for count in reasons.values():
            if isinstance(count, bool) or not isinstance(count, int) or count < 0:
                raise ValueError("bad_reasons must count")
        values["bad_reasons"] = {str(k)[:32]: v for k, v in reasons.items()}
    mode = data.get("mode")
    if mode is not None:
        if mode not in FC_MODES:
            raise ValueError("mode must be vtol, transition or aircraft")
        values["mode"] = mode
    lat, lon = values.get("lat"), values.get("lon")
    if (lat is not None and not -90 <= lat <= 90) or (lon is not None and not -180 <= lon <= 180):
        raise ValueError("lat/lon out of range")
    if "battery" in values and not 0 <= values["battery"] <= 100:
        raise ValueError("battery out of range")
    return FcReport(**values)


class ReturnLineParser:
    """Splits the bytes coming back on the line into reports. Never raises.

    Lines are newline-terminated JSON objects of at most MAX_RETURN_LINE bytes. A
    longer line is discarded up to its newline, a line that does not parse is dropped;
    both are counted in :attr:`bad_lines`. Not thread-safe: one reader feeds it; the
    latest good report is published as an immutable object.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._discarding = False
        self.lines = 0
        self.bad_lines = 0
        self.bytes = 0
        self.report: FcReport | None = None
        self.report_at: float | None = None

    def feed(self, data: bytes, now: float) -> None:
        """Take ``data`` received at monotonic time ``now``."""
        self.bytes += len(data)
        start = 0
        while True:
            newline = data.find(b"\n", start)
            chunk = data[start:] if newline < 0 else data[start:newline]
            if self._discarding:
                if newline >= 0:
                    self._discarding = False
            else:
                self._buffer += chunk
                if len(self._buffer) > MAX_RETURN_LINE:
                    # A huge line: drop what we have and everything up to its newline,
                    # so the buffer stays bounded whatever the other end sends.
                    self._buffer.clear()
                    self.bad_lines += 1
                    self._discarding = newline < 0
                elif newline >= 0:
                    self._line(bytes(self._buffer), now)
                    self._buffer.clear()
            if newline < 0:
                return
            start = newline + 1

    def _line(self, line: bytes, now: float) -> None:
        line = line.strip()
        if not line:
            return
        try:
            report = parse_report(line)
        except (ValueError, TypeError, RecursionError):
            self.bad_lines += 1
            return
        self.lines += 1
        self.report = report
        self.report_at = now


# --------------------------------------------------------------------------------------
# Options
# --------------------------------------------------------------------------------------

#: Where the simulated plane starts when the options give no ``origin`` (Leiria).
SIM_ORIGIN = (39.7436, -8.8071)

#: Keys of the agent config's ``adapter_options`` that the agent itself reads.
AGENT_OPTIONS = frozenset({"vehicle_type", "attributes"})


def _number(
    options: Mapping[str, Any],
    key: str,
    default: float,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
) -> float:
    value = options.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"spektrum option {key}: expected a number")
    if low is not None and (value <= low if low_open else value < low):
        raise ValueError(f"spektrum option {key}: must be {'>' if low_open else '>='} {low:g}")
    if high is not None and value > high:
        raise ValueError(f"spektrum option {key}: must be <= {high:g}")
    return float(value)


def _flag(options: Mapping[str, Any], key: str, default: bool = False) -> bool:
    # Strict: bool("false") is True, and a JSON slip must not switch a safety check off.
    value = options.get(key, default)
    if not isinstance(value, bool):
        raise ValueError(f"spektrum option {key}: expected true or false")
    return value


@dataclass(frozen=True)
class SpektrumConfig:
    """The adapter's options, checked. See ``docs/vehicles/vtol.md`` for each one."""

    simulate: bool = False
    simulator: str = "thread"  # or "process"
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
    # simulation
    origin: tuple[float, float] | None = None
    sim: Mapping[str, Any] = field(default_factory=dict)

    @property
    def system(self) -> int:
        return PROTOCOLS[self.protocol][0]

    @property
    def period_s(self) -> float:
        return self.frame_period_ms / 1000.0

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> SpektrumConfig:
        """Check ``options``; raises ValueError naming the first bad one."""
        protocol = options.get("protocol", "dsmx_2048")
        if protocol not in PROTOCOLS:
            raise ValueError(f"spektrum option protocol: one of {', '.join(sorted(PROTOCOLS))}")
        nominal = PROTOCOLS[protocol][1]
        period = _number(options, "frame_period_ms", nominal, low=5.0, high=50.0)
        if abs(period - nominal) > 0.2 * nominal:
            logger.warning(
                "spektrum: frame_period_ms %g differs from %s's nominal %g ms",
                period,
                protocol,
                nominal,
            )
        simulator = options.get("simulator", "thread")
        if simulator not in ("thread", "process"):
            raise ValueError("spektrum option simulator: 'thread' or 'process'")
        writer = options.get("writer", "auto")
        if writer not in ("auto", "thread", "process"):
            raise ValueError("spektrum option writer: 'auto', 'thread' or 'process'")
        port = options.get("port", "/dev/serial0")
        if not isinstance(port, str) or not port:
            raise ValueError("spektrum option port: a device path or pyserial URL")
        baudrate = options.get("baudrate", 115200)
        if isinstance(baudrate, bool) or not isinstance(baudrate, int) or baudrate <= 0:
            raise ValueError("spektrum option baudrate: a positive integer")

        def channel(key: str, default: str) -> int:
            name = options.get(key, default)
            if name not in SWITCH_CHANNELS:
                raise ValueError(f"spektrum option {key}: one of {', '.join(SWITCH_CHANNELS)}")
            return CHANNEL_NAMES.index(name)

        mode_channel = channel("mode_channel", "gear")
        arm_channel = channel("arm_channel", "aux1")
        if mode_channel == arm_channel:
            raise ValueError("spektrum options mode_channel and arm_channel must differ")
        reversed_names = options.get("reversed_channels", [])
        if not isinstance(reversed_names, Sequence) or isinstance(reversed_names, str):
            raise ValueError("spektrum option reversed_channels: a list of channel names")
        for name in reversed_names:
            if name not in CHANNEL_NAMES:
                raise ValueError(
                    f"spektrum option reversed_channels: {name!r} is not one of "
                    f"{', '.join(CHANNEL_NAMES)}"
                )
        origin = OptionReader("spektrum", options).origin()
        sim = options.get("sim", {})
        if not isinstance(sim, Mapping):
            raise ValueError("spektrum option sim: an object of simulator parameters")

        hold = _number(options, "stick_hold_ms", 250.0, low=20.0, high=5000.0)
        hold_max = _number(options, "stick_hold_max_ms", 1000.0, low=20.0, high=5000.0)
        if hold_max < hold:
            raise ValueError("spektrum option stick_hold_max_ms: must be >= stick_hold_ms")
        hover = _number(options, "hover_throttle", 0.5, low=0.05, high=0.95)
        land = _number(options, "land_throttle", 0.35, low=0.0, high=1.0)
        if land >= hover:
            raise ValueError("spektrum option land_throttle: must be below hover_throttle")
        config = cls(
            simulate=_flag(options, "simulate"),
            simulator=simulator,
            writer=writer,
            pump_realtime=_flag(options, "pump_realtime", True),
            pump_stale_s=_number(options, "pump_stale_s", 1.0, low=0.05, high=10.0),
            port=port,
            baudrate=baudrate,
            protocol=protocol,
            frame_period_ms=period,
            write_timeout_ms=_number(options, "write_timeout_ms", 50.0, low=0.0, low_open=True),
            throttle_step=_number(options, "throttle_step", 0.05, low=0.0, high=1.0, low_open=True),
            stick_deflection=_number(
                options, "stick_deflection", 0.5, low=0.0, high=1.0, low_open=True
            ),
            stick_hold_ms=hold,
            stick_hold_max_ms=hold_max,
            arm_max_throttle=_number(options, "arm_max_throttle", 0.05, low=0.0, high=0.3),
            mode_channel=mode_channel,
            arm_channel=arm_channel,
            reversed_channels=frozenset(CHANNEL_NAMES.index(n) for n in reversed_names),
            min_transition_altitude_m=_number(options, "min_transition_altitude_m", 20.0, low=0.0),
            allow_transition_without_altitude=_flag(options, "allow_transition_without_altitude"),
            hover_throttle=hover,
            cruise_throttle=_number(
                options, "cruise_throttle", 0.6, low=0.0, high=1.0, low_open=True
            ),
            max_climb_mps=_number(options, "max_climb_mps", 4.0, low=0.0, low_open=True),
            max_descent_mps=_number(options, "max_descent_mps", 4.0, low=0.0, low_open=True),
            vtol_max_speed_mps=_number(options, "vtol_max_speed_mps", 6.0, low=0.0, low_open=True),
            aircraft_climb_mps=_number(options, "aircraft_climb_mps", 5.0, low=0.0, low_open=True),
            transition_s=_number(options, "transition_s", 3.0, low=0.0, high=30.0),
            land_throttle=land,
            land_ramp_per_s=_number(options, "land_ramp_per_s", 0.25, low=0.0, low_open=True),
            land_timeout_s=_number(options, "land_timeout_s", 60.0, low=0.0, low_open=True),
            loop_watchdog_s=_number(options, "loop_watchdog_s", 2.0, low=0.0),
            telemetry_stale_s=_number(options, "telemetry_stale_s", 1.0, low=0.0, low_open=True),
            close_timeout_s=_number(options, "close_timeout_s", 30.0, low=0.0),
            origin=origin,
            sim=dict(sim),
        )
        unknown = set(options) - KNOWN_OPTIONS - AGENT_OPTIONS
        if unknown:
            # Warn rather than refuse (the options object is shared with the agent), but
            # loudly: a misspelt "min_transition_altitude_m" silently keeps the default.
            logger.warning("spektrum: unknown options ignored: %s", ", ".join(sorted(unknown)))
        return config

    def sim_params(self) -> dict[str, Any]:
        """The simulator's model parameters: the envelope shared with the adapter (so
        projections and landing agree with the model), then the ``sim`` overrides."""
        return {
            "hover_throttle": self.hover_throttle,
            "max_climb_mps": self.max_climb_mps,
            "max_descent_mps": self.max_descent_mps,
            "vtol_max_speed_mps": self.vtol_max_speed_mps,
            "aircraft_climb_mps": self.aircraft_climb_mps,
            "transition_s": self.transition_s,
            "failsafe_throttle": self.land_throttle,
            **self.sim,
        }


#: Every option :meth:`SpektrumConfig.from_options` reads.
KNOWN_OPTIONS = frozenset(f.name for f in fields(SpektrumConfig))


# --------------------------------------------------------------------------------------
# Stick state, landing sequence and the frame schedule
# --------------------------------------------------------------------------------------


@dataclass
class _Landing:
    cause: str
    phase: str  # "to_vtol", "descend", "cut"
    since: float


#: An envelope correction descends at this rate (VTOL and aircraft mode alike) ...
RECOVERY_DESCENT_MPS = 1.0
#: ... and flies back towards the geofence at this speed (VTOL mode).
RECOVERY_RETURN_MPS = 2.0
#: How fast a correction's descent setting adapts when the plane does not sink at
#: RECOVERY_DESCENT_MPS (an updraft): the change of vertical speed asked for per second,
#: per m/s of error (an integral controller; 2/s settles in about a second and stays
#: well damped with the FC's own lag and 20 Hz telemetry).
RECOVERY_SINK_GAIN = 2.0


@dataclass
class _Recovery:
    """An envelope correction the control thread flies until ``target`` is reached (see
    :meth:`FlightControls.recover`): ``limit`` is "altitude", "geofence" or "speed".
    ``throttle_cap`` (VTOL mode) and ``elevator_cap`` (aircraft mode) hold the descent;
    they adapt while the plane does not sink as it should."""

    limit: str
    target: float
    centre: tuple[float, float] | None
    throttle_cap: float
    elevator_cap: float


class FlightControls:
    """The virtual transmitter: stick positions, switches and the landing sequence.

    Shared by the event loop (commands) and the control thread (:meth:`tick` every
    10 ms; with the thread writer, once per frame). Every method takes :attr:`lock`
    (callers that mutate fields directly hold it too); none blocks or does I/O under it.

    Values: ``throttle`` 0..1, stick axes -1..1 (aileron +right, elevator +nose up i.e.
    stick back, rudder +right). Every one of them returns to its neutral once its hold
    time passes without a repeat (the key was released, the browser went away): the
    stick axes to centre, the throttle to :meth:`throttle_neutral` for the flight mode
    (VTOL mode: the hover setting in the air, idle on the ground; aircraft mode: the
    cruise setting). Nothing a user sends stays applied after the user stops sending.
    ``mode`` "vtol"/"aircraft"; ``armed``.
    """

    def __init__(self, config: SpektrumConfig) -> None:
        self.config = config
        self.lock = threading.Lock()
        #: Notified (under ``lock``) when the landing sequence disarms.
        self.landed = threading.Condition(self.lock)
        self.throttle = 0.0
        #: Where the throttle returns to, as of the last tick.
        self.neutral_throttle = 0.0
        self.axes = dict.fromkeys(STICK_AXES, 0.0)
        self._expires = dict.fromkeys(STICK_AXES, 0.0)
        # Until then the throttle keeps a user's setting; after, it follows the neutral.
        self._throttle_expires = 0.0
        # Hold-time bookkeeping per stick axis and for the throttle.
        self._last_press: dict[str, tuple[float, int]] = dict.fromkeys(
            (*STICK_AXES, "throttle"), (-1e9, 0)
        )
        self._repeat_s: dict[str, float | None] = dict.fromkeys((*STICK_AXES, "throttle"))
        # Whether the plane may be in the air, for when telemetry cannot tell.
        self._lifted = False
        self.mode = "vtol"
        self.armed = False
        self.landing: _Landing | None = None
        self.landings = 0
        self.last_cause: str | None = None
        #: Envelope corrections under way, by limit.
        self.recoveries: dict[str, _Recovery] = {}
        self.loop_beat = time.monotonic()
        self.servos: list[int] = self._servos()
        self._last_tick: float | None = None

    # --- the event loop's side ---------------------------------------------------------
    def _hold_locked(self, key: str, direction: int, now: float) -> float:
        """The hold time of a press of ``key`` (a stick axis or "throttle") in
        ``direction``: ``stick_hold_ms``, or longer when the client repeats a held key
        less often. The browser's repeat interval follows the round trip (100 ms at
        best), and a stick that returned to neutral between two repeats would stutter.
        It adapts to 1.5 x the observed repeat interval + 50 ms (a moving average of
        the gaps between same-direction presses), at most ``stick_hold_max_ms``."""
        cfg = self.config
        last_at, last_direction = self._last_press[key]
        gap = now - last_at
        if direction and direction == last_direction and gap < cfg.stick_hold_max_ms / 1000:
            seen = self._repeat_s[key]
            self._repeat_s[key] = gap if seen is None else 0.7 * seen + 0.3 * gap
        elif direction != last_direction:
            self._repeat_s[key] = None
        self._last_press[key] = (now, direction)
        hold = cfg.stick_hold_ms / 1000
        repeat = self._repeat_s[key]
        if repeat is not None:
            hold = min(max(hold, 1.5 * repeat + 0.05), cfg.stick_hold_max_ms / 1000)
        return hold

    def set_axis(self, axis: str, value: float, now: float) -> None:
        """Deflect ``axis`` to ``value`` for the hold time (a repeat extends it; see
        :meth:`_hold_locked`)."""
        value = max(-1.0, min(1.0, value)) if math.isfinite(value) else 0.0
        direction = (value > 0) - (value < 0)
        with self.lock:
            hold = self._hold_locked(axis, direction, now)
            self.axes[axis] = value
            self._expires[axis] = now + hold

    def throttle_after(self, delta: float) -> float:
        """The throttle one press of ``delta`` would set: a step from the current
        setting, or from the neutral when the press goes the other way (``s`` right
        after ``w`` descends at once instead of first undoing the climb)."""
        base = self.throttle
        if (delta > 0 and base < self.neutral_throttle) or (
            delta < 0 and base > self.neutral_throttle
        ):
            base = self.neutral_throttle
        return max(0.0, min(1.0, base + delta))

    def move_throttle_locked(self, delta: float, now: float) -> None:
        """Step the throttle by ``delta`` for the hold time of a press; after it the
        throttle returns to its neutral. The caller holds :attr:`lock`."""
        direction = (delta > 0) - (delta < 0)
        hold = self._hold_locked("throttle", direction, now)
        self.throttle = self.throttle_after(delta)
        self._throttle_expires = now + hold
        if self.mode == "vtol" and self.throttle > self.config.hover_throttle:
            self._lifted = True

    def centre(self) -> None:
        """Centre aileron, elevator and rudder at once."""
        with self.lock:
            self.centre_locked()

    def centre_locked(self) -> None:
        """:meth:`centre` for a caller that holds :attr:`lock`."""
        for axis in self.axes:
            self.axes[axis] = 0.0
            self._expires[axis] = 0.0

    def neutral_locked(self, fc: FcReport | None) -> None:
        """Sticks centred and the throttle at its neutral now (the caller holds
        :attr:`lock`); ``fc`` is the latest fresh report, or None."""
        self.centre_locked()
        self._throttle_expires = 0.0
        if self.landing is None:
            self.neutral_throttle = self.throttle_neutral(fc)
            self.throttle = self.neutral_throttle

    def throttle_neutral(self, fc: FcReport | None) -> float:
        """Where the throttle rests for the flight mode: VTOL mode in the air, the hover
        setting (the altitude holds); on the ground, idle; aircraft mode, the cruise
        setting (level flight); disarmed, idle. In the air or not: from telemetry, or
        without, from whether the throttle went past the hover setting since arming."""
        cfg = self.config
        if not self.armed:
            return 0.0
        if self.mode == "aircraft":
            return cfg.cruise_throttle
        if fc is not None and fc.on_ground is not None:
            self._lifted = not fc.on_ground
        return cfg.hover_throttle if self._lifted else 0.0

    def wait_disarmed(self, timeout: float) -> bool:
        """Block until disarmed (at most ``timeout`` s); True if disarmed."""
        with self.landed:
            return self.landed.wait_for(lambda: not self.armed, timeout)

    def beat(self, now: float) -> None:
        """The event loop is alive (see ``loop_watchdog_s``)."""
        with self.lock:
            self.loop_beat = now

    def start_landing(self, cause: str, now: float) -> bool:
        """Begin the landing sequence; False when there is nothing to land (disarmed)
        or it already runs. In aircraft mode: back to VTOL at the hover setting first."""
        with self.lock:
            return self._start_landing(cause, now)

    def _start_landing(self, cause: str, now: float) -> bool:
        self.centre_locked()
        self.recoveries.clear()  # the landing descends anyway, and owns the throttle
        if not self.armed:
            self.throttle = 0.0
            return False
        if self.landing is not None:
            return False
        self.last_cause = cause
        if self.mode == "aircraft":
            # Throttle means airspeed in aircraft mode; back in VTOL mode the hover
            # setting holds the altitude while the rotors tilt up, and the descent
            # ramp starts from there.
            self.mode = "vtol"
            self.throttle = self.config.hover_throttle
            self.landing = _Landing(cause, "to_vtol", now)
        else:
            self.landing = _Landing(cause, "descend", now)
        logger.warning("spektrum: landing (%s)", cause)
        return True

    def recover(self, breach: Breach, fc: FcReport | None, now: float) -> str:
        """Start (or keep up) the correction of an envelope breach; returns what it
        does, in words. The control thread flies it (:meth:`tick`) until the breach's
        target is reached, telemetry is lost or a landing starts.

        * altitude: the climb is cut at once (throttle to its neutral, elevator no
          higher than centre), then the plane descends at RECOVERY_DESCENT_MPS (VTOL
          mode: the throttle held below the hover setting; aircraft mode: the elevator
          held down) until it is ``breach.target`` high;
        * geofence: back to VTOL mode, sticks centred, then flown back towards the
          centre at RECOVERY_RETURN_MPS until ``breach.target`` from it;
        * speed: VTOL mode: the right stick centred until slower than the target;
          aircraft mode: back to VTOL mode (a plane cannot fly slower than it stalls).
        """
        cfg = self.config
        with self.lock:
            if self.landing is not None:
                return "none: the plane is landing"
            if not self.armed:
                return "none: the motors are disarmed"
            mode = self.mode
            again = breach.limit in self.recoveries
            if not again:
                self.recoveries[breach.limit] = _Recovery(
                    limit=breach.limit,
                    target=breach.target,
                    centre=breach.centre,
                    throttle_cap=self._throttle_for(-RECOVERY_DESCENT_MPS),
                    elevator_cap=-min(1.0, RECOVERY_DESCENT_MPS / cfg.aircraft_climb_mps),
                )
            if breach.limit == "altitude":
                self._throttle_expires = 0.0
                self.neutral_throttle = self.throttle_neutral(fc)
                self.throttle = min(self.throttle, self.neutral_throttle)
                self.axes["elevator"] = min(0.0, self.axes["elevator"])
                self._apply_recoveries(now, 0.0, fc)
                level = "hover" if mode == "vtol" else "level flight"
                return f"{level}, descending to {breach.target:.1f} m"
            if breach.limit == "geofence":
                self._apply_recoveries(now, 0.0, fc)
                what = "back to VTOL mode, " if mode == "aircraft" else ""
                return f"{what}flying back inside the geofence"
            self._apply_recoveries(now, 0.0, fc)
            if mode == "aircraft":
                return "back to VTOL mode: slowing down"
            return "sticks centred: slowing down"

    def _throttle_for(self, vz: float) -> float:
        """The VTOL throttle for vertical speed ``vz`` (inverse of the climb model)."""
        cfg = self.config
        if vz >= 0:
            return cfg.hover_throttle + vz / cfg.max_climb_mps * (1 - cfg.hover_throttle)
        return max(0.0, cfg.hover_throttle * (1 + vz / cfg.max_descent_mps))

    def _to_vtol_locked(self) -> None:
        if self.mode == "aircraft":
            logger.warning("spektrum: envelope: back to VTOL mode")
            self.mode = "vtol"
            self._throttle_expires = 0.0
            self.throttle = self.config.hover_throttle

    def _apply_recoveries(self, now: float, dt: float, fc: FcReport | None) -> None:
        """Fly the envelope corrections for one tick (the caller holds the lock)."""
        cfg = self.config
        for limit, rec in list(self.recoveries.items()):
            if fc is None:
                # Blind, a correction could fly the plane into the ground: level off
                # and let the agent's envelope start it again once telemetry is back.
                logger.warning("spektrum: envelope %s correction ends: no telemetry", limit)
                del self.recoveries[limit]
                continue
            if limit == "altitude":
                if fc.alt is None or fc.alt <= rec.target:
                    del self.recoveries[limit]
                    continue
                sink_error = 0.0 if fc.vz is None else fc.vz + RECOVERY_DESCENT_MPS
                if self.mode == "vtol":
                    per_throttle = cfg.max_descent_mps / cfg.hover_throttle  # m/s per unit
                    rec.throttle_cap -= RECOVERY_SINK_GAIN * sink_error / per_throttle * dt
                    rec.throttle_cap = max(0.0, min(cfg.hover_throttle, rec.throttle_cap))
                    self.throttle = min(self.throttle, rec.throttle_cap)
                else:
                    rec.elevator_cap -= (
                        RECOVERY_SINK_GAIN * sink_error / cfg.aircraft_climb_mps * dt
                    )
                    rec.elevator_cap = max(-1.0, min(0.0, rec.elevator_cap))
                    self.axes["elevator"] = min(self.axes["elevator"], rec.elevator_cap)
            elif limit == "speed":
                if fc.speed is None or fc.speed <= rec.target:
                    del self.recoveries[limit]
                    continue
                self._to_vtol_locked()
                self.axes["aileron"] = self.axes["elevator"] = 0.0
            else:
                if rec.centre is None or fc.lat is None or fc.lon is None:
                    del self.recoveries[limit]
                    continue
                north, east = local_offset_m((fc.lat, fc.lon), rec.centre)
                if math.hypot(north, east) <= rec.target:
                    self.axes["aileron"] = self.axes["elevator"] = 0.0
                    del self.recoveries[limit]
                    continue
                self._to_vtol_locked()
                if fc.heading is None:
                    self.axes["aileron"] = self.axes["elevator"] = 0.0
                    continue
                # Body-frame stick towards the centre: forward is stick forward
                # (elevator -), right is aileron +.
                bearing = math.atan2(east, north) - math.radians(fc.heading)
                amount = min(1.0, RECOVERY_RETURN_MPS / cfg.vtol_max_speed_mps)
                self.axes["elevator"] = -math.cos(bearing) * amount
                self.axes["aileron"] = math.sin(bearing) * amount

    # --- the writer thread's side ------------------------------------------------------
    def tick(self, now: float, fc: FcReport | None) -> list[int]:
        """Advance time to ``now`` (hold timeouts, landing, envelope corrections, loop
        watchdog) and return the eight servo positions to send. ``fc`` is the latest
        fresh report from the far end, or None when there is none."""
        cfg = self.config
        with self.lock:
            dt = 0.0 if self._last_tick is None else min(0.1, max(0.0, now - self._last_tick))
            self._last_tick = now
            for axis, expires in self._expires.items():
                if now >= expires:
                    self.axes[axis] = 0.0
            if not self.armed:
                self._lifted = False
            self.neutral_throttle = self.throttle_neutral(fc)
            if self.landing is None and now >= self._throttle_expires:
                # Released (or never pressed): the throttle rests at its neutral.
                self.throttle = self.neutral_throttle
            if (
                self.armed
                and self.landing is None
                and cfg.loop_watchdog_s > 0
                and now - self.loop_beat > cfg.loop_watchdog_s
            ):
                # The agent's event loop has hung: nobody would run the link-loss
                # fail-safe, so the thread lands the plane itself (the paper's
                # dedicated microcontroller does the same).
                self._start_landing("agent_stalled", now)
            if self.landing is not None:
                self._advance_landing(now, dt, fc)
            elif self.recoveries and self.armed:
                self._apply_recoveries(now, dt, fc)
            self.servos = self._servos()
            return list(self.servos)

    def _advance_landing(self, now: float, dt: float, fc: FcReport | None) -> None:
        cfg = self.config
        landing = self.landing
        assert landing is not None
        self.centre_locked()
        if not self.armed:
            self.landing = None
            return
        grounded = fc is not None and fc.on_ground is True
        if landing.phase == "to_vtol":
            if grounded:
                landing.phase, landing.since = "cut", now
            elif now - landing.since >= cfg.transition_s:
                landing.phase, landing.since = "descend", now
        if landing.phase == "descend":
            # Smoothly towards the descent setting (down from a climb, or up from a
            # faster descent), never a step.
            step = cfg.land_ramp_per_s * dt
            target = cfg.land_throttle
            self.throttle += max(-step, min(step, target - self.throttle))
            # Without telemetry (real plane, no sensor) ground contact is unknowable:
            # cut after land_timeout_s of descent.
            timed_out = fc is None and now - landing.since >= cfg.land_timeout_s
            if grounded or timed_out:
                landing.phase, landing.since = "cut", now
        if landing.phase == "cut":
            self.throttle = 0.0
            # Motors at idle for a moment before disarming, like a pilot would.
            if now - landing.since >= 0.3:
                self.armed = False
                self.landing = None
                self.landings += 1
                self.landed.notify_all()
                logger.warning("spektrum: landed and disarmed (%s)", landing.cause)

    def _servos(self) -> list[int]:
        cfg = self.config
        values = [SERVO_CENTRE] * CHANNEL_COUNT
        values[THROTTLE] = throttle_to_servo(self.throttle if self.armed else 0.0)
        for axis, channel in STICK_AXES.items():
            values[channel] = stick_to_servo(self.axes[axis])
        values[cfg.mode_channel] = SERVO_HIGH if self.mode == "aircraft" else SERVO_LOW
        values[cfg.arm_channel] = SERVO_HIGH if self.armed else SERVO_LOW
        for channel in cfg.reversed_channels:
            values[channel] = 2 * SERVO_CENTRE - values[channel]
        return [clamp_servo(v) for v in values]


@dataclass(frozen=True)
class FrameTiming:
    """Frame timing over a window: periods in ms between consecutive frame writes."""

    count: int
    mean_ms: float | None
    p99_dev_ms: float | None  # 99th percentile of |period - nominal|
    max_ms: float | None


def timing_of(stamps: Sequence[float], nominal_ms: float) -> FrameTiming:
    """Period statistics of monotonic write times ``stamps`` (seconds, ascending)."""
    periods = [(b - a) * 1000.0 for a, b in itertools.pairwise(stamps)]
    if not periods:
        return FrameTiming(0, None, None, None)
    devs = sorted(abs(p - nominal_ms) for p in periods)
    p99 = devs[min(len(devs) - 1, math.ceil(0.99 * len(devs)) - 1)]
    return FrameTiming(len(periods), sum(periods) / len(periods), p99, max(periods))


class FrameSchedule:
    """Deadlines on a fixed monotonic grid: ``start + k * period``.

    After each frame the next deadline is one period on, whatever time the frame
    actually went out, so a late wake-up never shifts the following frames and lateness
    does not accumulate. When a frame went out more than half a period late (a stall),
    whole grid slots are skipped rather than sending the next frame right behind it: a
    receiver delimits frames only by the silence between them and would merge the two.
    """

    def __init__(self, period_s: float, start: float) -> None:
        self.period = period_s
        self.next_at = start
        self.skipped = 0

    def advance(self, now: float) -> float:
        """The deadline after the slot just served at ``now``."""
        self.next_at += self.period
        if self.next_at - now < self.period / 2:
            skip = math.ceil((now + self.period / 2 - self.next_at) / self.period)
            self.next_at += skip * self.period
            self.skipped += skip
        return self.next_at


class FrameStats:
    """Counters and write times of the frames sent, shared between threads."""

    def __init__(self) -> None:
        self.frames = 0
        self.write_errors = 0
        self.skipped_slots = 0
        self.starved = 0
        self.realtime = False
        self.stamps: collections.deque[float] = collections.deque(maxlen=8192)
        self.changed = threading.Condition()

    def add(self, stamps: Sequence[float], *, errors: int = 0) -> None:
        with self.changed:
            self.stamps.extend(stamps)
            self.frames += len(stamps)
            self.write_errors += errors
            self.changed.notify_all()

    def wait_frames(self, count: int, timeout: float) -> bool:
        """Block until ``count`` more frames went out."""
        with self.changed:
            target = self.frames + count
            return self.changed.wait_for(lambda: self.frames >= target, timeout)


def _log_every(count: int) -> bool:
    return count in (1, 10, 100) or count % 1000 == 0


class _FrameWriter(threading.Thread):
    """The frame schedule on a thread of the agent's process (``writer: "thread"``,
    and for ports without a file descriptor such as ``loop://``).

    Each slot ticks the controls and writes one frame. It shares the interpreter lock
    with the event loop, so a CPU-heavy loop delays its wake-ups (the process writer
    does not have that problem).
    """

    def __init__(
        self, port: Any, controls: FlightControls, config: SpektrumConfig, fc: Any
    ) -> None:
        super().__init__(name="spektrum-writer", daemon=True)
        self.port = port
        self.controls = controls
        self.config = config
        self.fc = fc  # () -> FcReport | None
        self.stop_event = threading.Event()
        self.stats = FrameStats()

    def run(self) -> None:
        schedule = FrameSchedule(self.config.period_s, time.monotonic())
        phase = False
        while not self.stop_event.is_set():
            now = time.monotonic()
            try:
                values = self.controls.tick(now, self.fc())
                self.port.write(frame_for(values, phase=phase, system=self.config.system))
            except Exception as exc:  # a dead port must not kill the schedule
                self.stats.add((), errors=1)
                if _log_every(self.stats.write_errors):
                    logger.warning("spektrum: frame write failed: %s", exc)
            else:
                self.stats.add((now,))
                phase = not phase  # A, B, A, ... as received, whatever was lost
            next_at = schedule.advance(now)
            self.stats.skipped_slots = schedule.skipped
            self.stop_event.wait(next_at - time.monotonic())

    def publish(self, values: Sequence[int]) -> None:
        """Nothing to do: this writer ticks the controls itself at every frame."""

    def stop(self) -> None:
        self.stop_event.set()


def frame_for(values: Sequence[int], *, phase: bool, system: int) -> bytes:
    """Frame A (``phase`` False: channels 0..6) or B (channels 0..5 and 7) of the eight
    servo positions ``values``."""
    channels = FRAME_B_CHANNELS if phase else FRAME_A_CHANNELS
    return encode_frame([(c, values[c]) for c in channels], phase=phase, system=system)


#: A control record from the agent to the pump: magic, then the eight positions.
PUMP_RECORD = struct.Struct("<4s8H")
PUMP_MAGIC = b"SPK1"
#: The pump reports its counters and frame times this often.
PUMP_STATUS_S = 0.025
_PUMP_BOOT = (
    "import sys; from agents.vehicles.spektrum.adapter import frame_pump_main; "
    "sys.exit(frame_pump_main(sys.argv[1:]))"
)


def _child_env() -> dict[str, str]:
    """The environment for a child ``python``: this checkout importable as ``agents``."""
    root = str(Path(__file__).resolve().parents[3])
    path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PYTHONPATH": path}


class _FramePump:
    """The agent's side of the frame pump process (``writer: "process"``).

    The pump is the paper's dedicated microcontroller: a small process that only writes
    frames on the schedule, with its own interpreter (so the event loop, the video
    encoder or a burst of commands cannot delay it) and, when permitted, real-time
    scheduling. It writes to the port's file descriptor, inherited. The agent sends it
    the eight servo positions over a pipe whenever the controls tick (every 10 ms and
    after each command); it sends back its counters and frame times every 25 ms.

    If the agent stops sending (hung, killed) for ``pump_stale_s``, the pump stops
    writing frames, exactly like a receiver that lost its transmitter: the FC then runs
    its own receiver-loss fail-safe. It exits when the agent closes the pipe or dies.
    """

    def __init__(self, port_fd: int, config: SpektrumConfig) -> None:
        self.port_fd = port_fd
        self.config = config
        self.stats = FrameStats()
        self.process: subprocess.Popen[bytes] | None = None
        self.dropped = 0
        self._control: int | None = None
        self._status: int | None = None
        self._reader: threading.Thread | None = None

    def start(self) -> None:
        cfg = self.config
        control_r, control_w = os.pipe()
        status_r, status_w = os.pipe()
        args = [
            "--port-fd", str(self.port_fd),
            "--control-fd", str(control_r),
            "--status-fd", str(status_w),
            "--period-ms", repr(cfg.frame_period_ms),
            "--system", str(cfg.system),
            "--stale-s", repr(cfg.pump_stale_s),
        ]  # fmt: skip
        if cfg.pump_realtime:
            args.append("--realtime")
        try:
            self.process = subprocess.Popen(
                [sys.executable, "-c", _PUMP_BOOT, *args],
                pass_fds=(self.port_fd, control_r, status_w),
                stdin=subprocess.DEVNULL,
                env=_child_env(),
            )
        except BaseException:
            for fd in (control_r, control_w, status_r, status_w):
                os.close(fd)
            raise
        os.close(control_r)
        os.close(status_w)
        os.set_blocking(control_w, False)
        self._control, self._status = control_w, status_r
        self._reader = threading.Thread(target=self._read_status, name="spektrum-pump-status")
        self._reader.daemon = True
        self._reader.start()

    def publish(self, values: Sequence[int]) -> None:
        """Send the positions to the pump. Never blocks: 20-byte writes to a pipe are
        atomic, and if the pipe is full (the pump is stuck) the record is dropped."""
        fd = self._control
        if fd is None:
            return
        try:
            os.write(fd, PUMP_RECORD.pack(PUMP_MAGIC, *values))
        except (BlockingIOError, BrokenPipeError, OSError):
            self.dropped += 1
            if _log_every(self.dropped):
                logger.warning("spektrum: frame pump not taking positions (%d)", self.dropped)

    def _read_status(self) -> None:
        fd = self._status
        assert fd is not None
        buffer = b""
        while True:
            try:
                data = os.read(fd, 65536)
            except OSError:
                return
            if not data:
                return  # the pump exited
            buffer += data
            *lines, buffer = buffer.split(b"\n")
            if len(buffer) > 1 << 20:
                buffer = b""  # never from our own pump; bounded anyway
            for line in lines:
                self._status_line(line)

    def _status_line(self, line: bytes) -> None:
        try:
            status = json.loads(line)
            stamps = [float(t) for t in status["stamps"]]
            errors = int(status["errors"])
        except (ValueError, TypeError, KeyError):
            return
        stats = self.stats
        stats.skipped_slots = int(status.get("skipped", 0))
        stats.starved = int(status.get("starved", 0))
        stats.realtime = bool(status.get("realtime", False))
        stats.add(stamps, errors=max(0, errors - stats.write_errors))

    def is_alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def stop(self) -> None:
        """Close the control pipe: the pump sees end-of-file and exits."""
        fd, self._control = self._control, None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)

    def join(self, timeout: float) -> None:
        """Wait for the pump to exit (killing it after ``timeout``), then its reader."""
        self.stop()
        if self.process is not None:
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        if self._reader is not None:
            self._reader.join(timeout)
        fd, self._status = self._status, None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)


def frame_pump_main(argv: Sequence[str]) -> int:
    """The frame pump process (see :class:`_FramePump`). Returns 0 when the agent
    closed the control pipe, 2 on bad arguments."""
    import argparse
    import select

    parser = argparse.ArgumentParser(prog="spektrum frame pump")
    parser.add_argument("--port-fd", type=int, required=True)
    parser.add_argument("--control-fd", type=int, required=True)
    parser.add_argument("--status-fd", type=int, required=True)
    parser.add_argument("--period-ms", type=float, default=11.0)
    parser.add_argument("--system", type=int, default=SYSTEM_DSMX_11MS)
    parser.add_argument("--stale-s", type=float, default=1.0)
    parser.add_argument("--realtime", action="store_true")
    args = parser.parse_args(list(argv))
    realtime = False
    if args.realtime:
        # SCHED_FIFO: woken on time even when every core is busy. Needs root or
        # CAP_SYS_NICE; without, the pump still has its own interpreter.
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
            realtime = True
        except (AttributeError, OSError):
            pass
    control, status, port = args.control_fd, args.status_fd, args.port_fd
    os.set_blocking(control, False)
    os.set_blocking(status, False)
    period = args.period_ms / 1000.0
    values: tuple[int, ...] | None = None
    received_at = 0.0
    buffer = b""
    phase = False
    stamps: list[float] = []
    errors = starved = 0
    schedule = FrameSchedule(period, time.monotonic())
    status_at = schedule.next_at + PUMP_STATUS_S
    while True:
        timeout = max(0.0, min(schedule.next_at, status_at) - time.monotonic())
        ready, _, _ = select.select([control], [], [], timeout)
        if ready:
            try:
                data = os.read(control, 4096)
            except BlockingIOError:
                data = None
            if data == b"":
                return 0  # the agent closed the pipe (or died): stop sending frames
            buffer += data or b""
            while len(buffer) >= PUMP_RECORD.size:
                magic, *positions = PUMP_RECORD.unpack_from(buffer)
                if magic != PUMP_MAGIC:
                    buffer = buffer[1:]  # resynchronise; never expected on a pipe
                    continue
                buffer = buffer[PUMP_RECORD.size :]
                values = tuple(clamp_servo(p) for p in positions)
                received_at = time.monotonic()
        now = time.monotonic()
        if now >= schedule.next_at:
            if values is not None and now - received_at <= args.stale_s:
                try:
                    os.write(port, frame_for(values, phase=phase, system=args.system))
                    stamps.append(now)
                    phase = not phase  # A, B, A, ... as received, whatever was lost
                except OSError:
                    errors += 1
            else:
                starved += 1
            schedule.advance(now)
        if now >= status_at:
            line = json.dumps(
                {
                    "stamps": stamps,
                    "errors": errors,
                    "skipped": schedule.skipped,
                    "starved": starved,
                    "realtime": realtime,
                }
            )
            try:
                os.write(status, line.encode() + b"\n")
                stamps = []
            except BlockingIOError:
                pass  # the agent is not reading: keep the times for the next report
            except OSError:
                return 0  # the agent is gone
            if len(stamps) > 4096:
                stamps = stamps[-4096:]
            status_at = max(status_at + PUMP_STATUS_S, now)


class _ControlTicker(threading.Thread):
    """With the pump: ticks the controls every 10 ms (hold timeouts, landing, the loop
    watchdog) and publishes the positions. Not time-critical; the pump keeps the frame
    timing."""

    def __init__(self, controls: FlightControls, pump: _FramePump, fc: Any) -> None:
        super().__init__(name="spektrum-controls", daemon=True)
        self.controls = controls
        self.pump = pump
        self.fc = fc
        self.stop_event = threading.Event()

    def run(self) -> None:
        while not self.stop_event.is_set():
            try:
                self.pump.publish(self.controls.tick(time.monotonic(), self.fc()))
            except Exception:  # keep ticking: a dead ticker would freeze the sticks
                logger.exception("spektrum: control tick failed")
            self.stop_event.wait(0.01)


class _ReturnReader(threading.Thread):
    """Reads the return line into a :class:`ReturnLineParser` until stopped."""

    def __init__(self, port: Any, parser: ReturnLineParser) -> None:
        super().__init__(name="spektrum-reader", daemon=True)
        self.port = port
        self.parser = parser
        self.stop_event = threading.Event()
        self.errors = 0

    def run(self) -> None:
        while not self.stop_event.is_set():
            try:
                waiting = self.port.in_waiting
                data = self.port.read(max(1, min(int(waiting), 4096)))
                if data:
                    self.parser.feed(bytes(data), time.monotonic())
            except Exception as exc:  # a flaky or closed line must not end the agent
                if self.stop_event.is_set():
                    return
                self.errors += 1
                if self.errors in (1, 10, 100) or self.errors % 1000 == 0:
                    logger.warning("spektrum: return line read failed: %s", exc)
                self.stop_event.wait(0.1)


# --------------------------------------------------------------------------------------
# Commands
# --------------------------------------------------------------------------------------

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

#: :meth:`SpektrumAdapter.start` fails when no frame went out within this time.
START_TIMEOUT_S = 10.0
#: ``arm`` waits this long for the FC to report armed before giving up ...
ARM_WAIT_S = 1.0
#: ... or, with no telemetry (the real plane), holds the throttle at idle this long.
ARM_SETTLE_S = 0.25

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


class SpektrumAdapter(Adapter):
    """The Spektrum VTOL plane; see the module docstring and ``docs/vehicles/vtol.md``.

    After :meth:`start` frames are flowing: :attr:`controls` is the virtual transmitter,
    :attr:`writer` the frame writer (pump process or thread), :attr:`simulator` the
    in-process simulator (``simulate`` with the thread simulator, else None) and
    :attr:`sim_process` the simulator process (``simulator: "process"``).
    """

    name = "spektrum"

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.config = SpektrumConfig.from_options(options)
        self.controls = FlightControls(self.config)
        self.parser = ReturnLineParser()
        self.port: Any = None
        self.simulator: Any = None
        self.sim_process: subprocess.Popen[bytes] | None = None
        #: The frame writer: the pump process, or the thread fallback.
        self.writer: _FramePump | _FrameWriter | None = None
        self._ticker: _ControlTicker | None = None
        self._reader: _ReturnReader | None = None
        self._pty_fds: list[int] = []
        self._beat_task: asyncio.Task[None] | None = None

    # --- lifecycle ---------------------------------------------------------------------
    async def start(self) -> None:
        """Open the port (in simulation: a pty with the simulator on its far end), start
        the frame writer, the control and reader threads, and return once frames flow.
        Raises AdapterError ``hardware`` when the port cannot be opened or no frame can
        be written within START_TIMEOUT_S (everything started is closed again)."""
        cfg = self.config
        try:
            path = self._start_simulator() if cfg.simulate else cfg.port
            self.port = serial.serial_for_url(
                path,
                baudrate=cfg.baudrate,
                bytesize=8,
                parity="N",
                stopbits=1,
                timeout=0.05,
                write_timeout=cfg.write_timeout_ms / 1000.0,
            )
        except (OSError, ValueError, serial.SerialException) as exc:
            await self.close()
            raise AdapterError(f"cannot open the receiver port: {exc}", code="hardware") from exc
        self.controls.beat(time.monotonic())
        self.controls.tick(time.monotonic(), None)
        fd = self._port_fd()
        if cfg.writer == "process" and fd is None:
            await self.close()
            raise AdapterError(
                f"writer 'process' needs a port with a file descriptor, not {cfg.port!r}",
                code="hardware",
            )
        try:
            if fd is not None and cfg.writer in ("auto", "process"):
                pump = _FramePump(fd, cfg)
                self.writer = pump
                pump.start()
                self._ticker = _ControlTicker(self.controls, pump, self.fc_report)
                self._ticker.start()
            else:
                self.writer = _FrameWriter(self.port, self.controls, cfg, self.fc_report)
                self.writer.start()
        except OSError as exc:
            await self.close()
            raise AdapterError(f"cannot start the frame writer: {exc}", code="hardware") from exc
        self._reader = _ReturnReader(self.port, self.parser)
        self._reader.start()
        self._beat_task = asyncio.create_task(self._beat(), name="spektrum-loop-beat")
        # Started means frames are flowing (the pump takes a moment to start).
        if not await asyncio.to_thread(self.writer.stats.wait_frames, 2, START_TIMEOUT_S):
            await self.close()
            raise AdapterError("no frame could be written to the receiver port", code="hardware")

    def _port_fd(self) -> int | None:
        """The port's file descriptor; None for pyserial URL handlers without one."""
        if os.name != "posix":
            return None
        try:
            fd = self.port.fileno()
        except Exception:  # loop://, socket:// ...: pyserial raises its own errors
            return None
        return fd if isinstance(fd, int) and fd >= 0 else None

    def _push(self) -> None:
        """Send the controls to the pump now rather than at its next tick, so a command
        reaches the next frame (the thread writer ticks at every frame anyway)."""
        writer = self.writer
        if isinstance(writer, _FramePump):
            writer.publish(self.controls.tick(time.monotonic(), self.fc_report()))

    def _start_simulator(self) -> str:
        """Create a pty pair, put the simulator on the master side; returns the slave's
        path for pyserial (the same code path as a real UART)."""
        from agents.vehicles.spektrum.sim.simulator import FdLink, SpektrumSimulator

        cfg = self.config
        master, slave = os.openpty()
        self._pty_fds += [master, slave]
        # Raw at once: until pyserial configures the slave, the line discipline would
        # echo and translate bytes.
        tty.setraw(slave)
        # Keep our slave fd open for the adapter's life: with no slave open the master
        # reads EIO, which the simulator would see as a broken line.
        path = os.ttyname(slave)
        origin = cfg.origin or SIM_ORIGIN
        if cfg.simulator == "process":
            self.sim_process = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "agents",
                    "sim",
                    "spektrum",
                    "--fd",
                    str(master),
                    "--origin",
                    f"{origin[0]},{origin[1]}",
                    "--period-ms",
                    str(cfg.frame_period_ms),
                    "--system",
                    str(cfg.system),
                    "--params",
                    json.dumps(cfg.sim_params()),
                    "--quiet",
                    *(["--realtime"] if cfg.pump_realtime else []),
                ],
                pass_fds=(master,),
                stdin=subprocess.DEVNULL,
                env=_child_env(),
            )
            os.close(master)  # the child has its own copy
            self._pty_fds.remove(master)
        else:
            self.simulator = SpektrumSimulator(
                FdLink(master),
                origin=origin,
                params=cfg.sim_params(),
                frame_period_ms=cfg.frame_period_ms,
                system=cfg.system,
            )
            self._pty_fds.remove(master)  # the simulator owns and closes it
            self.simulator.start()
        return path

    async def _beat(self) -> None:
        while True:
            self.controls.beat(time.monotonic())
            await asyncio.sleep(0.1)

    async def close(self) -> None:
        """Land first if the plane may be flying (up to ``close_timeout_s``), then stop
        the frame writer, the threads and the simulator and close the port and the pty.
        Safe to call more than once.

        Once frames stop, the FC sees a receiver loss and runs its own fail-safe.
        """
        writer = self.writer
        if (
            writer is not None
            and writer.is_alive()
            and self.controls.armed
            and not self._known_on_ground()
        ):
            self.controls.start_landing("shutdown", time.monotonic())
            await asyncio.to_thread(self.controls.wait_disarmed, self.config.close_timeout_s)
        if self._beat_task is not None:
            self._beat_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._beat_task
            self._beat_task = None
        for thread in (self._ticker, self._reader):
            if thread is not None:
                thread.stop_event.set()
        if writer is not None:
            writer.stop()
        if self.port is not None:
            with contextlib.suppress(Exception):
                getattr(self.port, "cancel_read", lambda: None)()
        joinable: list[_ControlTicker | _ReturnReader | _FramePump | _FrameWriter | None]
        joinable = [self._ticker, self._reader, writer]
        for part in joinable:
            if part is not None:
                await asyncio.to_thread(part.join, 3.0)
        self.writer = self._ticker = self._reader = None
        if self.port is not None:
            with contextlib.suppress(Exception):
                self.port.close()
            self.port = None
        if self.simulator is not None:
            await asyncio.to_thread(self.simulator.close)
            self.simulator = None
        if self.sim_process is not None:
            self.sim_process.terminate()
            try:
                await asyncio.to_thread(self.sim_process.wait, 3.0)
            except subprocess.TimeoutExpired:
                self.sim_process.kill()
                await asyncio.to_thread(self.sim_process.wait)
            self.sim_process = None
        for fd in self._pty_fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self._pty_fds.clear()

    # --- reading -------------------------------------------------------------------------
    def fc_report(self) -> FcReport | None:
        """The latest report from the far end if it is fresh (``telemetry_stale_s``)."""
        report, at = self.parser.report, self.parser.report_at
        if report is None or at is None:
            return None
        if time.monotonic() - at > self.config.telemetry_stale_s:
            return None
        return report

    def _known_on_ground(self) -> bool:
        fc = self.fc_report()
        return fc is not None and fc.on_ground is True

    def _airborne(self) -> bool | None:
        """True/False from fresh telemetry; None when unknown."""
        fc = self.fc_report()
        if fc is None or fc.on_ground is None:
            return None
        return not fc.on_ground

    def frame_timing(self, since: float | None = None) -> FrameTiming:
        """Period statistics of the frames written since monotonic time ``since``
        (default: the last 8192 frames). With the pump, its times arrive every 25 ms."""
        if self.writer is None:
            return FrameTiming(0, None, None, None)
        stamps = [t for t in list(self.writer.stats.stamps) if since is None or t >= since]
        return timing_of(stamps, self.config.frame_period_ms)

    @property
    def frame_stats(self) -> FrameStats | None:
        """The writer's counters (frames, write errors, skipped slots, ...)."""
        return None if self.writer is None else self.writer.stats

    @property
    def frames_written(self) -> int:
        return 0 if self.writer is None else self.writer.stats.frames

    @property
    def bad_return_lines(self) -> int:
        """Malformed lines received on the return line and ignored."""
        return self.parser.bad_lines

    def wait_frames(self, count: int = 2, timeout: float = 1.0) -> bool:
        """Block until ``count`` more frames are known to have gone out."""
        return self.writer is not None and self.writer.stats.wait_frames(count, timeout)

    # --- vocabulary ----------------------------------------------------------------------
    def commands(self) -> list[CommandSpec]:
        """Stick, mode and set-up commands; see docs/vehicles/vtol.md for the mapping."""
        cfg = self.config
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

    def telemetry_topics(self) -> list[str]:
        return list(TELEMETRY_TOPICS)

    def state(self) -> VehicleState:
        """Position, altitude, heading, speed and battery from fresh telemetry (None on
        the real plane without a sensor); armed and mode as commanded."""
        fc = self.fc_report()
        origin = self.config.origin or (SIM_ORIGIN if self.config.simulate else None)
        return VehicleState(
            lat=None if fc is None else fc.lat,
            lon=None if fc is None else fc.lon,
            alt=None if fc is None else fc.alt,
            heading_deg=None if fc is None else fc.heading,
            speed_mps=None if fc is None else fc.speed,
            battery=None if fc is None else fc.battery,
            armed=self._armed(fc),
            mode=self.controls.mode,
            home=origin,
        )

    def _armed(self, fc: FcReport | None) -> bool:
        # The FC may refuse to arm (throttle up); when it reports, believe it.
        if fc is not None and fc.armed is not None:
            return fc.armed
        return self.controls.armed

    def telemetry(self) -> dict[str, Any]:
        """Every topic of :data:`TELEMETRY_TOPICS`; None where unknown."""
        fc = self.fc_report()
        controls = self.controls
        timing = self.frame_timing_recent()

        def rounded(value: float | None, digits: int) -> float | None:
            return None if value is None else round(value, digits)

        location = None
        if fc is not None and fc.lat is not None and fc.lon is not None:
            location = {"lat": round(fc.lat, 7), "lon": round(fc.lon, 7)}
        servos = list(controls.servos)
        return {
            "altitude": rounded(None if fc is None else fc.alt, 2),
            "speed": rounded(None if fc is None else fc.speed, 2),
            "heading": rounded(None if fc is None else fc.heading, 1),
            "flight_mode": controls.mode,
            "is_armed": self._armed(fc),
            "throttle": round(controls.throttle if controls.armed else 0.0, 3),
            "channels": dict(zip(CHANNEL_NAMES, servos, strict=True)),
            "frame_period_ms": rounded(timing.mean_ms, 2),
            "battery_level": rounded(None if fc is None else fc.battery, 1),
            "location": location,
            "landing": controls.landing is not None,
        }

    def frame_timing_recent(self) -> FrameTiming:
        """Timing of the last second of frames."""
        return self.frame_timing(since=time.monotonic() - 1.0)

    # --- acting --------------------------------------------------------------------------
    async def execute(self, name: str, args: Mapping[str, Any]) -> None:
        """Apply a command to the virtual transmitter; the next frame (within one
        period) carries it.

        Raises AdapterError: ``not_ready`` before start, ``landing`` while a landing
        sequence runs, ``not_armed`` for throttle_up or the aircraft mode while
        disarmed, ``unsafe`` for arming with the throttle up, disarming in the air or
        the aircraft mode below ``min_transition_altitude_m`` (or with the altitude
        unknown), ``unknown_command``.
        """
        if self.writer is None:
            raise AdapterError("the plane is not started", code="not_ready")
        try:
            await self._execute(name, args)
        finally:
            self._push()

    async def _execute(self, name: str, args: Mapping[str, Any]) -> None:
        now = time.monotonic()
        controls = self.controls
        cfg = self.config
        if name == "land":
            controls.start_landing("user", now)
            return
        if name == "stop":
            # The browser sends it as the last key goes up. During a landing the
            # sequence owns the sticks already: nothing to do, nothing to refuse.
            with controls.lock:
                controls.neutral_locked(self.fc_report())
            return
        if controls.landing is not None:
            raise AdapterError(
                "the plane is landing; wait until it has landed and disarmed", code="landing"
            )
        if name in STICK_COMMANDS:
            axis, sign = STICK_COMMANDS[name]
            amount = float(args.get("amount", cfg.stick_deflection))
            controls.set_axis(axis, sign * amount, now)
        elif name in ("throttle_up", "throttle_down"):
            step = float(args.get("step", cfg.throttle_step))
            with controls.lock:
                if name == "throttle_up" and not controls.armed:
                    raise AdapterError("arm the motors first", code="not_armed")
                controls.move_throttle_locked(step if name == "throttle_up" else -step, now)
        elif name == "change_to_vtol_mode":
            with controls.lock:
                if controls.mode == "aircraft":
                    controls.mode = "vtol"
                    # See FlightControls._start_landing: hover holds the altitude.
                    controls.throttle = cfg.hover_throttle if controls.armed else 0.0
        elif name == "change_to_aircraft_mode":
            self._check_transition()
            with controls.lock:
                controls.mode = "aircraft"
        elif name == "arm":
            with controls.lock:
                if controls.throttle > cfg.arm_max_throttle:
                    raise AdapterError("lower the throttle to idle before arming", code="unsafe")
                controls.armed = True
                controls.throttle = 0.0
            self._push()
            await self._await_armed()
        elif name == "disarm":
            airborne = self._airborne()
            with controls.lock:
                if airborne or (airborne is None and controls.throttle > cfg.arm_max_throttle):
                    raise AdapterError(
                        "the plane may be flying: land first (disarming would drop it)",
                        code="unsafe",
                    )
                controls.armed = False
                controls.throttle = 0.0
                controls.landed.notify_all()
        else:
            raise AdapterError(f"{name!r} is not a command of this plane", code="unknown_command")

    async def _await_armed(self) -> None:
        """Hold the throttle at idle until the FC has armed. FCs arm only when they see
        the arm switch with the throttle low, and a throttle_up queued right behind
        ``arm`` would otherwise reach the FC in the same frame. With telemetry: until
        it reports armed (AdapterError ``autopilot_refused`` after ARM_WAIT_S); without:
        ARM_SETTLE_S, many frames."""
        deadline = time.monotonic() + ARM_WAIT_S
        settle = time.monotonic() + ARM_SETTLE_S
        while True:
            fc = self.fc_report()
            if fc is not None and fc.armed is True:
                return
            now = time.monotonic()
            if fc is None and now >= settle:
                return
            if now >= deadline:
                with self.controls.lock:
                    self.controls.armed = False
                raise AdapterError("the flight controller did not arm", code="autopilot_refused")
            await asyncio.sleep(0.01)

    def _check_transition(self) -> None:
        cfg = self.config
        if self.controls.mode == "aircraft":
            return
        if not self.controls.armed:
            raise AdapterError("arm and take off first", code="not_armed")
        fc = self.fc_report()
        alt = None if fc is None else fc.alt
        if alt is None:
            if cfg.allow_transition_without_altitude:
                return
            raise AdapterError(
                "altitude unknown: the aircraft mode needs at least "
                f"{cfg.min_transition_altitude_m:g} m",
                code="unsafe",
            )
        if alt < cfg.min_transition_altitude_m:
            raise AdapterError(
                f"too low for the aircraft mode: {alt:.1f} m, at least "
                f"{cfg.min_transition_altitude_m:g} m",
                code="unsafe",
            )

    async def safe_action(self, action: str) -> None:
        """Land, whatever the action: a plane cannot stop in the air, and over the
        receiver line it has no navigation to fly home. Returns at once; the control
        thread flies the landing (see :meth:`FlightControls.tick`), so the hub is not
        held up and a hung event loop cannot stop it."""
        if action != "land":
            logger.info("spektrum: safe action %r carried out as land", action)
        self.controls.start_landing(f"safe_action:{action}", time.monotonic())
        self._push()

    async def neutral(self) -> None:
        """Centre the sticks and the throttle (see :meth:`FlightControls.throttle_neutral`):
        the new controller starts from a hover, or level flight in aircraft mode."""
        fc = self.fc_report()
        with self.controls.lock:
            self.controls.neutral_locked(fc)
        self._push()

    async def envelope_recover(self, breach: Breach) -> str:
        """Correct a breach of the task's ceiling, geofence or speed from the control
        thread (see :meth:`FlightControls.recover`): cut the climb to hover (VTOL mode)
        or level flight (aircraft mode) and descend below the ceiling; fly back inside
        the geofence in VTOL mode; slow down (VTOL mode). Returns at once."""
        action = self.controls.recover(breach, self.fc_report(), time.monotonic())
        self._push()
        return action

    def project(self, name: str, args: Mapping[str, Any]) -> Projection | None:
        """Where a command takes the plane over the next second, for the agent's
        altitude ceiling and geofence: throttle_up (VTOL: the climb rate of the new
        throttle; aircraft: the current climb) and pitch_up in aircraft mode give an
        altitude; the right stick in VTOL mode a position. None without telemetry or
        for other commands. In aircraft mode no position is projected: the plane flies
        on whatever the user does, and refusing a turn would not keep it inside."""
        fc = self.fc_report()
        if fc is None:
            return None
        cfg = self.config
        mode = self.controls.mode
        vz = max(0.0, fc.vz or 0.0)
        if name == "throttle_up" and fc.alt is not None:
            if mode == "vtol":
                throttle = self.controls.throttle_after(float(args.get("step", 0)))
                vz = max(vz, self._climb_rate(throttle))
            return Projection(alt=fc.alt + vz)
        if name == "pitch_up" and mode == "aircraft" and fc.alt is not None:
            amount = float(args.get("amount", cfg.stick_deflection))
            return Projection(alt=fc.alt + max(vz, amount * cfg.aircraft_climb_mps))
        if name in STICK_COMMANDS and name != "yaw_left" and name != "yaw_right":
            if mode != "vtol" or fc.lat is None or fc.lon is None or fc.heading is None:
                return None
            axis, sign = STICK_COMMANDS[name]
            speed = float(args.get("amount", cfg.stick_deflection)) * cfg.vtol_max_speed_mps
            # Elevator +1 (stick back) flies backwards; aileron +1 slides right.
            forward = -sign * speed if axis == "elevator" else 0.0
            right = sign * speed if axis == "aileron" else 0.0
            h = math.radians(fc.heading)
            north = forward * math.cos(h) - right * math.sin(h)
            east = forward * math.sin(h) + right * math.cos(h)
            lat, lon = offset((fc.lat, fc.lon), north, east)
            return Projection(lat=lat, lon=lon, alt=fc.alt)
        return None

    def _climb_rate(self, throttle: float) -> float:
        """Vertical speed of the VTOL model at ``throttle`` (shared with the sim)."""
        cfg = self.config
        if throttle >= cfg.hover_throttle:
            return (throttle - cfg.hover_throttle) / (1 - cfg.hover_throttle) * cfg.max_climb_mps
        return (throttle - cfg.hover_throttle) / cfg.hover_throttle * cfg.max_descent_mps
