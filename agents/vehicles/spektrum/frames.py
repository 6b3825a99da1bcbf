"""The Spektrum remote receiver wire format: DSMX 2048 frames and servo positions.

**DSMX 2048, 11 ms** ("remote receiver" serial format, Spektrum's *Specification for
Spektrum Remote Receiver Interfacing*; see ``docs/vehicles/vtol.md`` for the layout and
sources). We chose it over SRXL2 because it is what the paper describes (a
unidirectional line from receiver to FC), it needs no handshake, device IDs or CRC
negotiation with a closed FC that we cannot inspect, and every FC that takes a Spektrum
satellite decodes it. 115200 baud 8N1; every ``frame_period_ms`` one 16-byte frame::

    byte 0      fades (lost-frame counter of a real receiver; always 0 here)
    byte 1      system: 0xB2 = DSMX 11 ms 2048, 0xA2 = DSMX 22 ms 2048
    bytes 2..15 seven big-endian servo words:
                bit 15      phase: set in the first word of the second frame of a pair
                bits 14..11 channel id (0 throttle, 1 aileron, 2 elevator, 3 rudder,
                            4 gear, 5 aux1, 6 aux2, 7 aux3)
                bits 10..0  servo position 0..2047 (centre 1024; 342..1706 = 100 %
                            travel = about 1100..1900 us)

Eight channels do not fit seven slots, so frames alternate: A carries channels 0..6, B
(phase bit set) channels 0..5 and 7 (:func:`frame_for`). Sticks, mode and arm switch
therefore go out in every frame; aux2/aux3 (unused, centred) every other one.

Shared by the adapter (encoding) and the simulator (decoding); pure Python.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

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


def frame_for(values: Sequence[int], *, phase: bool, system: int) -> bytes:
    """Frame A (``phase`` False: channels 0..6) or B (channels 0..5 and 7) of the eight
    servo positions ``values``."""
    channels = FRAME_B_CHANNELS if phase else FRAME_A_CHANNELS
    return encode_frame([(c, values[c]) for c in channels], phase=phase, system=system)
