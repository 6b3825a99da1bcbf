"""The receiver side of the Spektrum VTOL plane: a flight controller on the far end of a
serial line (normally one side of a pty).

:class:`SpektrumSimulator` stands where the E-flite Convergence's flight controller (FC)
is. It

* splits the incoming bytes into frames the way FCs do (a frame is 16 bytes after a
  quiet gap; Spektrum frames carry no sync byte) and checks each one: size, system
  byte, channel ids, no duplicates, the phase bit alternating A/B, each A+B pair
  covering all eight channels, positions inside 100 % travel. Bad frames are counted by
  reason and ignored;
* measures the frame timing: mean period, p99 of |period - nominal| ("jitter") and the
  longest gap over a sliding window;
* flies :class:`VtolModel` with the decoded channels (VTOL hover and airplane modes,
  transition, stall, ground contact, battery, arming, the FC's own receiver-loss
  fail-safe);
* writes its state back as one JSON object per line at ``report_hz`` (the format
  :func:`agents.vehicles.spektrum.adapter.parse_report` reads).

Threads: :meth:`SpektrumSimulator.start` runs it on its own thread (the adapter's
``simulate`` default); :func:`cli` runs it in the foreground (``python -m agents sim
spektrum --port /dev/pts/N``), also used as the adapter's ``simulator: "process"``
where the timing it measures is not disturbed by the agent's own threads.

Timing caveat: a pty has no baud rate, so the measured period is when the bytes became
readable here. In-process, the simulator's thread shares the interpreter lock with the
agent, and its own wake-up latency adds to what it measures; use the process variant
for figures.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import errno
import json
import logging
import math
import os
import select
import signal
import sys
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, Protocol

from agents.geo import offset
from agents.vehicles.spektrum.adapter import (
    AILERON,
    AUX1,
    CHANNEL_COUNT,
    CHANNEL_NAMES,
    ELEVATOR,
    FRAME_SIZE,
    GEAR,
    RUDDER,
    SERVO_CENTRE,
    SERVO_HIGH,
    SERVO_LOW,
    SYSTEM_DSMX_11MS,
    THROTTLE,
    FrameError,
    decode_frame,
    servo_to_stick,
    servo_to_throttle,
)

logger = logging.getLogger(__name__)

GRAVITY = 9.81
#: A new frame starts after this much silence on the line, as in older ArduPilot
#: releases (today's resynchronises after 5 ms, PX4 after more than 5 ms; the gap only
#: matters while searching for a frame start, see docs/vehicles/vtol.md); frames are
#: 11 ms apart and take 1.4 ms at 115200 baud.
FRAME_GAP_S = 0.002
#: A servo position this far past centre is "switch on" (gear, aux).
SWITCH_THRESHOLD = 200


# --------------------------------------------------------------------------------------
# The line
# --------------------------------------------------------------------------------------


class Link(Protocol):
    """The simulator's end of the serial line."""

    def read(self, timeout: float) -> bytes:
        """Bytes available within ``timeout`` seconds (b"" if none). Raises OSError
        when the line is broken."""

    def write(self, data: bytes) -> bool:
        """Write without blocking; False when the data was dropped (line full)."""

    def close(self) -> None:
        """Release the line."""


class FdLink:
    """A file descriptor: a pty master, or one inherited from the agent (owned: closed
    by :meth:`close`)."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        # Non-blocking writes: a report must never stall the simulator when nobody
        # reads the other end (the adapter closed it, or is not reading yet).
        os.set_blocking(fd, False)
        self._closed = False

    def read(self, timeout: float) -> bytes:
        ready, _, _ = select.select([self.fd], [], [], max(0.0, timeout))
        if not ready:
            return b""
        try:
            data = os.read(self.fd, 4096)
        except BlockingIOError:
            return b""
        if not data:
            # End of file: readable for ever. Raise, so the caller backs off instead
            # of spinning (it may run with real-time priority).
            raise OSError(errno.EIO, "end of file on the line")
        return data

    def write(self, data: bytes) -> bool:
        try:
            return os.write(self.fd, data) == len(data)
        except (BlockingIOError, InterruptedError):
            return False

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            with contextlib.suppress(OSError):
                os.close(self.fd)


class SerialLink:
    """A serial port opened by pyserial (a device path or a pyserial URL)."""

    def __init__(self, port: str, baudrate: int = 115200) -> None:
        import serial  # type: ignore[import-untyped, unused-ignore]

        self.port: Any = serial.serial_for_url(port, baudrate=baudrate, timeout=0, write_timeout=0)

    def read(self, timeout: float) -> bytes:
        fileno = getattr(self.port, "fileno", None)
        if fileno is not None:
            try:
                fd = fileno()
            except Exception:  # URL handlers without a descriptor: poll below
                fd = None
            if fd is not None:
                ready, _, _ = select.select([fd], [], [], max(0.0, timeout))
                data = bytes(self.port.read(4096)) if ready else b""
                if ready and not data:
                    raise OSError(errno.EIO, "the port is readable but gives nothing")
                return data
        # URL handlers without a file descriptor (loop://): poll.
        data = bytes(self.port.read(4096))
        if not data:
            time.sleep(min(timeout, 0.001))
        return data

    def write(self, data: bytes) -> bool:
        try:
            return bool(self.port.write(data) == len(data))
        except Exception:  # pyserial's write timeout: drop the report
            return False

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.port.close()


# --------------------------------------------------------------------------------------
# Framing and timing checks
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TimingStats:
    """Frame periods over the window: mean, p99 of |period - nominal|, longest gap."""

    count: int
    period_ms: float | None
    jitter_ms: float | None
    max_gap_ms: float | None


class FrameChecker:
    """Splits received bytes into frames by the gap between them and checks them.

    Counters: :attr:`frames` (good), :attr:`bad` by reason (``short`` an incomplete
    frame before a gap, ``long`` bytes past 16 without a gap, ``size``/``channel_id``/
    ``duplicate``/``empty`` from the decoder, ``system`` a wrong system byte, ``phase``
    two frames of the same phase in a row, ``pair`` an A+B pair missing a channel),
    :attr:`out_of_travel` (good frames with a position outside 342..1706),
    :attr:`close_frames` (frames received right behind the previous one, without the
    quiet gap: decoded, but their timing is not measured).
    """

    def __init__(
        self, *, system: int = SYSTEM_DSMX_11MS, frame_period_ms: float = 11.0, window: int = 1000
    ) -> None:
        self.system = system
        self.nominal_ms = frame_period_ms
        self.frames = 0
        self.bad: collections.Counter[str] = collections.Counter()
        self.out_of_travel = 0
        self.close_frames = 0
        self.channels: dict[int, int] = {}
        self.last_good_at: float | None = None
        self._buffer = bytearray()
        self._last_byte_at: float | None = None
        self._burst_at = 0.0
        self._burst_frames = 0
        self._burst_timed = False
        self._last_phase: bool | None = None
        self._phase_a_ids: frozenset[int] | None = None
        self._last_frame_at: float | None = None
        self._periods: collections.deque[float] = collections.deque(maxlen=window)

    @property
    def bad_frames(self) -> int:
        return sum(self.bad.values())

    def feed(self, data: bytes, now: float) -> None:
        """Take ``data`` that became readable at monotonic time ``now``."""
        if not data:
            return
        gap = self._last_byte_at is None or now - self._last_byte_at >= FRAME_GAP_S
        self._last_byte_at = now
        if gap:
            if self._buffer:
                # Left over after a whole frame: a burst too long; else a frame cut short.
                self.bad["long" if self._burst_frames else "short"] += 1
                self._buffer.clear()
            self._burst_at = now
            self._burst_frames = 0
            # A lone frame (or its first bytes): its arrival time is its time.
            self._burst_timed = len(data) <= FRAME_SIZE
        self._buffer += data
        while len(self._buffer) >= FRAME_SIZE:
            block = bytes(self._buffer[:FRAME_SIZE])
            del self._buffer[:FRAME_SIZE]
            if self._burst_frames == 0:
                self._frame(block, self._burst_at, timed=self._burst_timed)
            else:
                # A whole frame right behind another, with no quiet gap as this end saw
                # it. The writer never does that (it skips a slot rather); on a pty it is
                # this reader or the kernel delivering late. Decoded (every block is
                # checked), not timed.
                self.close_frames += 1
                self._frame(block, now, timed=False)
            self._burst_frames += 1

    def _frame(self, block: bytes, now: float, *, timed: bool) -> None:
        try:
            frame = decode_frame(block)
        except FrameError as exc:
            self.bad[exc.reason] += 1
            return
        if frame.system != self.system:
            self.bad["system"] += 1
            return
        if self._last_phase is not None and frame.phase == self._last_phase:
            self.bad["phase"] += 1
        self._last_phase = frame.phase
        ids = frozenset(frame.servos)
        if not frame.phase:
            self._phase_a_ids = ids
        elif self._phase_a_ids is not None and self._phase_a_ids | ids != frozenset(
            range(CHANNEL_COUNT)
        ):
            self.bad["pair"] += 1
        if any(not SERVO_LOW <= v <= SERVO_HIGH for v in frame.servos.values()):
            self.out_of_travel += 1
        self.frames += 1
        self.channels.update(frame.servos)
        if timed:
            if self._last_frame_at is not None:
                self._periods.append((now - self._last_frame_at) * 1000.0)
            self._last_frame_at = now
        else:
            self._last_frame_at = None  # the next period would be wrong too
        self.last_good_at = now

    def timing(self) -> TimingStats:
        periods = list(self._periods)
        if not periods:
            return TimingStats(0, None, None, None)
        devs = sorted(abs(p - self.nominal_ms) for p in periods)
        p99 = devs[min(len(devs) - 1, math.ceil(0.99 * len(devs)) - 1)]
        return TimingStats(len(periods), sum(periods) / len(periods), p99, max(periods))

    def reset_timing(self) -> None:
        """Forget the measured periods (a measurement starts afresh)."""
        self._periods.clear()
        self._last_frame_at = None


# --------------------------------------------------------------------------------------
# The flight model
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SimParams:
    """The model's parameters. The first group is shared with the adapter (it projects
    and lands with the same numbers); the rest is the simulator's own."""

    hover_throttle: float = 0.5
    max_climb_mps: float = 4.0  # at full throttle in VTOL mode
    max_descent_mps: float = 4.0  # at idle in VTOL mode
    vtol_max_speed_mps: float = 6.0  # horizontal, full right stick in VTOL mode
    aircraft_climb_mps: float = 5.0  # full elevator in aircraft mode
    transition_s: float = 3.0  # rotors tilting forward
    failsafe_throttle: float = 0.35  # the FC's own descent on receiver loss
    vtol_yaw_rate_dps: float = 90.0
    cruise_speed_mps: float = 22.0  # airspeed at full throttle
    stall_speed_mps: float = 9.0
    stall_sink_mps: float = 6.0
    max_bank_deg: float = 45.0
    rudder_rate_dps: float = 15.0
    hard_landing_mps: float = 3.0
    crash_speed_mps: float = 12.0
    battery_pct: float = 100.0
    battery_drain_pct_per_s: float = 0.25  # at full throttle
    arm_max_throttle: float = 0.1
    failsafe_after_s: float = 0.5  # no good frame for this long: receiver loss
    heading_deg: float = 0.0
    #: Rising air in flight, m/s: the wind the agent's envelope must answer (tests
    #: change :attr:`VtolModel.updraft_mps` while flying, as a gust).
    updraft_mps: float = 0.0

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> SimParams:
        """Parameters from a JSON-friendly mapping; raises ValueError naming an
        unknown key or a non-number."""
        known = {f.name for f in fields(cls)}
        out: dict[str, float] = {}
        for key, value in values.items():
            if key not in known:
                raise ValueError(f"unknown simulator parameter {key!r}")
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"simulator parameter {key}: expected a number")
            if not math.isfinite(value):
                raise ValueError(f"simulator parameter {key}: expected a finite number")
            out[key] = float(value)
        params = cls(**out)
        if not 0 < params.hover_throttle < 1:
            raise ValueError("simulator parameter hover_throttle: between 0 and 1")
        return params


@dataclass(frozen=True)
class Inputs:
    """The FC's view of the sticks: throttle 0..1, aileron/elevator/rudder -1..1
    (elevator +1 = stick back, nose up), the two switches."""

    throttle: float = 0.0
    aileron: float = 0.0
    elevator: float = 0.0
    rudder: float = 0.0
    aircraft: bool = False
    arm: bool = False

    @classmethod
    def from_channels(
        cls, channels: Mapping[int, int], *, mode_channel: int = GEAR, arm_channel: int = AUX1
    ) -> Inputs:
        def get(channel: int, default: int) -> int:
            return channels.get(channel, default)

        return cls(
            throttle=servo_to_throttle(get(THROTTLE, SERVO_LOW)),
            aileron=servo_to_stick(get(AILERON, SERVO_CENTRE)),
            elevator=servo_to_stick(get(ELEVATOR, SERVO_CENTRE)),
            rudder=servo_to_stick(get(RUDDER, SERVO_CENTRE)),
            aircraft=get(mode_channel, SERVO_LOW) > SERVO_CENTRE + SWITCH_THRESHOLD,
            arm=get(arm_channel, SERVO_LOW) > SERVO_CENTRE + SWITCH_THRESHOLD,
        )


def _approach(value: float, target: float, dt: float, tau: float) -> float:
    """First-order lag of time constant ``tau``."""
    return value + (target - value) * min(1.0, dt / tau)


class VtolModel:
    """A point-mass VTOL plane, good enough to make telemetry respond sensibly.

    VTOL mode: throttle sets the vertical speed (hover at ``hover_throttle``), the
    right stick a horizontal velocity in the body frame, the rudder a yaw rate.
    Transition: the rotors tilt forward over ``transition_s`` while the altitude holds
    and the plane accelerates past the stall speed. Aircraft mode: throttle sets the
    airspeed, the elevator the climb rate, the ailerons a bank and so a coordinated turn
    (rate g*tan(bank)/v); below ``stall_speed_mps`` it stalls (sinks, controls dead).
    Disarmed or with an empty battery the motors are off. Arming needs the throttle at
    idle when the arm switch goes on (else it stays disarmed until the switch cycles).
    Touch-downs faster than ``hard_landing_mps`` vertically are hard landings; in
    aircraft mode faster than ``crash_speed_mps`` a crash. In the air, ``updraft_mps``
    adds to the vertical speed whatever the controls say.
    Conventions: metres north/east of the origin, heading clockwise from north.
    """

    def __init__(self, params: SimParams, origin: tuple[float, float]) -> None:
        self.p = params
        self.origin = origin
        self.north = 0.0
        self.east = 0.0
        self.alt = 0.0
        self.vz = 0.0
        self.v_forward = 0.0
        self.v_right = 0.0
        self.heading = params.heading_deg % 360.0
        self.mode = "vtol"  # vtol, transition, aircraft
        self.transition_t = 0.0
        self.armed = False
        self.arm_refused = 0
        self._arm_blocked = False
        self.battery = params.battery_pct
        self.on_ground = True
        self.stalled = False
        self.crashed = False
        self.hard_landings = 0
        self.fc_failsafe = False
        self.updraft_mps = params.updraft_mps

    @property
    def position(self) -> tuple[float, float]:
        return offset(self.origin, self.north, self.east)

    @property
    def speed(self) -> float:
        return math.hypot(self.v_forward, self.v_right)

    def climb_rate(self, throttle: float) -> float:
        p = self.p
        if throttle >= p.hover_throttle:
            return (throttle - p.hover_throttle) / (1 - p.hover_throttle) * p.max_climb_mps
        return (throttle - p.hover_throttle) / p.hover_throttle * p.max_descent_mps

    def step(self, dt: float, inputs: Inputs, *, link_ok: bool = True) -> None:
        """Advance ``dt`` seconds with ``inputs``; without a link the FC's own
        fail-safe flies (VTOL, sticks centred, descend, disarm on the ground)."""
        if dt <= 0 or self.crashed:
            return
        p = self.p
        self.fc_failsafe = not link_ok
        if not link_ok:
            inputs = Inputs(
                throttle=p.failsafe_throttle if not self.on_ground else 0.0,
                arm=self.armed and not self.on_ground,
            )
        self._arming(inputs)
        self._mode(dt, inputs)
        power = self.armed and self.battery > 0.0
        throttle = inputs.throttle if power else 0.0
        if power:
            self.battery = max(
                0.0, self.battery - (0.02 + throttle * p.battery_drain_pct_per_s) * dt
            )
        if self.mode == "aircraft":
            vz_target, turn = self._aircraft(dt, inputs, power)
        elif self.mode == "transition":
            vz_target, turn = self._transition(dt, inputs, power)
        else:
            vz_target, turn = self._vtol(dt, inputs, power)
        if not self.on_ground:
            vz_target += self.updraft_mps
        if self.on_ground and vz_target <= 0:
            vz_target = 0.0
        self.vz = _approach(self.vz, vz_target, dt, 0.3)
        if self.on_ground:
            turn = 0.0 if self.speed < 0.5 else turn
        mid = math.radians(self.heading + turn * dt / 2)
        self.heading = (self.heading + turn * dt) % 360.0
        self.north += (self.v_forward * math.cos(mid) - self.v_right * math.sin(mid)) * dt
        self.east += (self.v_forward * math.sin(mid) + self.v_right * math.cos(mid)) * dt
        self.alt += self.vz * dt
        if self.alt <= 0.0:
            self._touch_down()
        else:
            self.on_ground = False

    def _arming(self, inputs: Inputs) -> None:
        if not inputs.arm:
            self.armed = False
            self._arm_blocked = False
        elif not self.armed and not self._arm_blocked:
            if inputs.throttle <= self.p.arm_max_throttle:
                self.armed = True
            else:
                # Real FCs refuse to arm with the throttle up; cycle the switch.
                self._arm_blocked = True
                self.arm_refused += 1

    def _mode(self, dt: float, inputs: Inputs) -> None:
        if not inputs.aircraft:
            self.mode = "vtol"
            self.transition_t = 0.0
        elif self.mode == "vtol":
            self.mode = "transition"
            self.transition_t = 0.0
        if self.mode == "transition":
            self.transition_t += dt
            if self.transition_t >= self.p.transition_s:
                self.mode = "aircraft"

    def _vtol(self, dt: float, inputs: Inputs, power: bool) -> tuple[float, float]:
        p = self.p
        self.stalled = False
        if not power:
            self.v_forward = _approach(self.v_forward, 0.0, dt, 2.0)
            self.v_right = _approach(self.v_right, 0.0, dt, 2.0)
            return -2 * p.max_descent_mps, 0.0
        if self.on_ground and self.climb_rate(inputs.throttle) <= 0:
            self.v_forward = self.v_right = 0.0  # on its skids
            return 0.0, 0.0
        self.v_forward = _approach(self.v_forward, -inputs.elevator * p.vtol_max_speed_mps, dt, 0.6)
        self.v_right = _approach(self.v_right, inputs.aileron * p.vtol_max_speed_mps, dt, 0.6)
        return self.climb_rate(inputs.throttle), inputs.rudder * p.vtol_yaw_rate_dps

    def _transition(self, dt: float, inputs: Inputs, power: bool) -> tuple[float, float]:
        p = self.p
        self.stalled = False
        if not power:
            return self._vtol(dt, inputs, power)
        # The tilting rotors still carry the weight; thrust goes into speed.
        target = max(1.2 * p.stall_speed_mps, inputs.throttle * p.cruise_speed_mps)
        accel = target / max(p.transition_s, 0.1)
        self.v_forward = min(target, self.v_forward + accel * dt)
        self.v_right = _approach(self.v_right, 0.0, dt, 0.5)
        return inputs.elevator * p.aircraft_climb_mps * 0.5, inputs.rudder * p.rudder_rate_dps

    def _aircraft(self, dt: float, inputs: Inputs, power: bool) -> tuple[float, float]:
        p = self.p
        thrust = inputs.throttle if power else 0.0
        drag_tau = 2.0 if not self.on_ground else 1.0
        self.v_forward = _approach(self.v_forward, thrust * p.cruise_speed_mps, dt, drag_tau)
        self.v_right = 0.0
        self.stalled = self.v_forward < p.stall_speed_mps and not self.on_ground
        if self.stalled:
            return -p.stall_sink_mps, 0.0
        if self.on_ground and self.v_forward < p.stall_speed_mps:
            return 0.0, 0.0
        bank = math.radians(inputs.aileron * p.max_bank_deg)
        turn = math.degrees(GRAVITY * math.tan(bank) / max(self.v_forward, 1.0))
        return inputs.elevator * p.aircraft_climb_mps, turn + inputs.rudder * p.rudder_rate_dps

    def _touch_down(self) -> None:
        self.alt = 0.0
        if not self.on_ground:
            if self.mode == "aircraft" and self.v_forward > self.p.crash_speed_mps:
                logger.warning("simulated VTOL crashed at %.1f m/s", self.v_forward)
                self.crashed = True
                self.armed = False
                self.v_forward = self.v_right = 0.0
            elif self.vz < -self.p.hard_landing_mps:
                self.hard_landings += 1
                logger.warning("simulated VTOL landed hard at %.1f m/s", -self.vz)
        self.vz = max(0.0, self.vz)
        self.on_ground = True
        if self.mode != "aircraft":
            self.v_forward = self.v_right = 0.0


# --------------------------------------------------------------------------------------
# The simulator
# --------------------------------------------------------------------------------------


class SpektrumSimulator:
    """The FC end of the line: frames in, a flying model, JSON state lines out.

    ``link`` is owned (closed by :meth:`close`). ``params`` is a :class:`SimParams` or a
    mapping of its fields. Thread-safety: :meth:`snapshot`, :attr:`checker` counters
    and :attr:`model` may be read from other threads (values may be a step old).
    """

    def __init__(
        self,
        link: Link,
        *,
        origin: tuple[float, float],
        params: SimParams | Mapping[str, Any] | None = None,
        frame_period_ms: float = 11.0,
        system: int = SYSTEM_DSMX_11MS,
        mode_channel: int = GEAR,
        arm_channel: int = AUX1,
        step_hz: float = 50.0,
        report_hz: float = 20.0,
        window: int = 1000,
    ) -> None:
        if params is None:
            params = SimParams()
        elif not isinstance(params, SimParams):
            params = SimParams.from_mapping(params)
        self.link = link
        self.params = params
        self.model = VtolModel(params, origin)
        self.checker = FrameChecker(system=system, frame_period_ms=frame_period_ms, window=window)
        self.mode_channel = mode_channel
        self.arm_channel = arm_channel
        self.step_s = 1.0 / step_hz
        self.report_s = 1.0 / report_hz
        self.reports_sent = 0
        self.reports_dropped = 0
        self.link_errors = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._started_at = time.monotonic()
        self._lock = threading.Lock()
        self._snapshot: dict[str, Any] = {}

    # --- lifecycle ---------------------------------------------------------------------
    def start(self) -> None:
        """Run on a daemon thread until :meth:`close`."""
        self._thread = threading.Thread(target=self.run, name="spektrum-sim", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the thread (if any) and close the line. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        self.link.close()

    def stop(self) -> None:
        """Ask :meth:`run` to return."""
        self._stop.set()

    @property
    def running(self) -> bool:
        """Whether the thread started by :meth:`start` is alive."""
        return self._thread is not None and self._thread.is_alive()

    # --- the loop ----------------------------------------------------------------------
    def run(self) -> None:
        """Read, check, fly and report until stopped. Never raises for anything that
        comes in on the line; a broken line is retried every 50 ms."""
        now = time.monotonic()
        self._started_at = now
        last_step = now
        next_step = now + self.step_s
        next_report = now
        while not self._stop.is_set():
            timeout = min(next_step, next_report) - time.monotonic()
            try:
                data = self.link.read(max(0.0, timeout))
            except OSError as exc:
                # EIO: no one has the other side open (yet, or any more).
                self.link_errors += 1
                if exc.errno not in (errno.EIO, errno.EBADF) and self.link_errors < 3:
                    logger.warning("spektrum sim: line read failed: %s", exc)
                self._stop.wait(0.05)
                data = b""
            now = time.monotonic()
            if data:
                try:
                    self.checker.feed(data, now)
                except Exception:  # a checker bug must not take the FC down
                    logger.exception("spektrum sim: frame check failed")
            if now >= next_step:
                try:
                    self._step(min(now - last_step, 0.1), now)
                except Exception:
                    logger.exception("spektrum sim: model step failed")
                last_step = now
                next_step = max(next_step + self.step_s, now + self.step_s / 2)
            if now >= next_report:
                self._report()
                next_report = max(next_report + self.report_s, now + self.report_s / 2)

    def _step(self, dt: float, now: float) -> None:
        last = self.checker.last_good_at
        link_ok = last is not None and now - last <= self.params.failsafe_after_s
        inputs = Inputs.from_channels(
            self.checker.channels, mode_channel=self.mode_channel, arm_channel=self.arm_channel
        )
        self.model.step(dt, inputs, link_ok=link_ok)
        with self._lock:
            self._snapshot = self._state()

    def _state(self) -> dict[str, Any]:
        m = self.model
        timing = self.checker.timing()
        lat, lon = m.position

        def r(value: float | None, digits: int) -> float | None:
            return None if value is None else round(value, digits)

        return {
            "alt": round(m.alt, 3),
            "vz": round(m.vz, 3),
            "speed": round(m.speed, 3),
            "airspeed": round(m.v_forward, 3),
            "heading": round(m.heading, 2),
            "lat": round(lat, 8),
            "lon": round(lon, 8),
            "mode": m.mode,
            "armed": m.armed,
            "on_ground": m.on_ground,
            "battery": round(m.battery, 2),
            "stalled": m.stalled,
            "crashed": m.crashed,
            "hard_landings": m.hard_landings,
            "arm_refused": m.arm_refused,
            "fc_failsafe": m.fc_failsafe,
            "frames": self.checker.frames,
            "bad_frames": self.checker.bad_frames,
            "bad_reasons": dict(self.checker.bad),
            "close_frames": self.checker.close_frames,
            "out_of_travel": self.checker.out_of_travel,
            "period_ms": r(timing.period_ms, 3),
            "jitter_ms": r(timing.jitter_ms, 3),
            "max_gap_ms": r(timing.max_gap_ms, 3),
        }

    def _report(self) -> None:
        with self._lock:
            state = dict(self._snapshot) or self._state()
        line = json.dumps(state, separators=(",", ":")).encode() + b"\n"
        try:
            if self.link.write(line):
                self.reports_sent += 1
            else:
                self.reports_dropped += 1
        except OSError:
            self.reports_dropped += 1

    # --- reading from other threads ----------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        """The state as last reported (the JSON line's fields)."""
        with self._lock:
            return dict(self._snapshot)

    def channels(self) -> dict[str, int]:
        """The last decoded servo position of every channel received, by name."""
        return {CHANNEL_NAMES[c]: v for c, v in sorted(self.checker.channels.items())}


# --------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------


def _origin(text: str) -> tuple[float, float]:
    try:
        lat, lon = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("expected LAT,LON") from None
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise argparse.ArgumentTypeError("latitude or longitude out of range")
    return (lat, lon)


def cli(argv: list[str]) -> int:
    """``python -m agents sim spektrum``: run the simulated FC on a serial port.

    Returns 0 when stopped (Ctrl-C or SIGTERM), 2 on bad arguments or a port that
    cannot be opened.
    """
    parser = argparse.ArgumentParser(
        prog="python -m agents sim spektrum",
        description="Simulated Spektrum-fed VTOL flight controller on a serial port. "
        "Make a pty pair with `socat -d -d pty,raw,echo=0 pty,raw,echo=0`, give one end "
        "here and the other to the agent's spektrum adapter as its port.",
    )
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--port", help="serial device or pyserial URL, e.g. /dev/pts/3")
    where.add_argument("--fd", type=int, help="an inherited file descriptor (the adapter's)")
    parser.add_argument("--baudrate", type=int, default=115200)
    parser.add_argument("--origin", type=_origin, default=(39.7436, -8.8071), help="LAT,LON")
    parser.add_argument("--period-ms", type=float, default=11.0, help="nominal frame period")
    parser.add_argument("--system", type=int, default=SYSTEM_DSMX_11MS, help="system byte")
    parser.add_argument("--params", default="{}", help="JSON object of model parameters")
    parser.add_argument("--status-every", type=float, default=1.0, help="seconds; 0: never")
    parser.add_argument("--quiet", action="store_true", help="no status lines")
    parser.add_argument(
        "--realtime",
        action="store_true",
        help="SCHED_FIFO if permitted, so the timing measured is the line's, not this "
        "process's wake-up latency on a busy machine",
    )
    parser.add_argument("--log-level", default="WARNING")
    args = parser.parse_args(argv)
    if args.realtime:
        with contextlib.suppress(AttributeError, OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(5))
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s: %(message)s")
    try:
        params = SimParams.from_mapping(json.loads(args.params))
    except (ValueError, TypeError, AttributeError) as exc:
        print(f"--params: {exc}", file=sys.stderr)
        return 2
    link: Link
    try:
        link = FdLink(args.fd) if args.fd is not None else SerialLink(args.port, args.baudrate)
    except Exception as exc:  # pyserial raises its own SerialException
        print(f"cannot open the line: {exc}", file=sys.stderr)
        return 2
    sim = SpektrumSimulator(
        link,
        origin=args.origin,
        params=params,
        frame_period_ms=args.period_ms,
        system=args.system,
    )
    # SIGTERM (the adapter closing its subprocess, systemd) stops cleanly like Ctrl-C.
    signal.signal(signal.SIGTERM, lambda *_: sim.stop())
    sim.start()
    try:
        while sim.running:
            time.sleep(args.status_every if args.status_every > 0 else 0.5)
            if not args.quiet and args.status_every > 0:
                print(_status_line(sim), file=sys.stderr, flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        sim.close()
    return 0


def _status_line(sim: SpektrumSimulator) -> str:
    s = sim.snapshot()
    if not s:
        return "no state yet"
    bad = ",".join(f"{k}={v}" for k, v in sorted(sim.checker.bad.items())) or "0"
    return (
        f"{s['mode']:<10} armed={s['armed']!s:<5} alt={s['alt']:7.2f} m "
        f"speed={s['speed']:5.2f} m/s hdg={s['heading']:6.1f} bat={s['battery']:5.1f}% | "
        f"frames={s['frames']} bad={bad} period={s['period_ms']} ms "
        f"p99|dev|={s['jitter_ms']} ms max_gap={s['max_gap_ms']} ms | "
        f"{json.dumps(sim.channels())}"
    )


__all__ = [
    "FdLink",
    "FrameChecker",
    "Inputs",
    "SerialLink",
    "SimParams",
    "SpektrumSimulator",
    "TimingStats",
    "VtolModel",
    "cli",
]
