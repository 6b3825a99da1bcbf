"""Adapter for the paper's Spektrum VTOL plane (section 4.2.3), over a serial port.

The E-flite Convergence VTOL has a closed flight controller (FC) that expects a Spektrum
remote receiver on its receiver port. The paper replaced that receiver with a
microcontroller writing Spektrum frames; this adapter does the same job from the agent's
computer through a UART (pyserial), so users fly the plane with two virtual sticks.

The pieces, a file each: the wire format (:mod:`.frames`), the options (:mod:`.config`),
the commands (:mod:`.vocabulary`), the virtual transmitter (:mod:`.controls`), getting
frames out on time (:mod:`.pump`) and what comes back on the line (:mod:`.report`). The
event loop only changes the stick state under a lock; the control thread and the frame
pump keep the 11 ms schedule.

Telemetry: the Convergence's FC sends nothing back over the receiver line, so on the
real plane altitude, speed, position and battery are unknown (``None``) unless a
companion sensor writes JSON lines onto the return line. The simulator
(:mod:`agents.vehicles.spektrum.sim`) sits on the far end of a pty, decodes the frames,
checks their framing and timing, flies a VTOL/airplane model and reports its state back
as those lines.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import time
from collections.abc import Mapping
from typing import Any

# pyserial ships no type hints of its own (types-pyserial adds them when installed).
import serial  # type: ignore[import-untyped, unused-ignore]

from agents.geo import offset
from agents.telemetry import TopicInfo
from agents.vehicles.base import (
    Adapter,
    AdapterError,
    Breach,
    CommandSpec,
    Projection,
    VehicleState,
)
from agents.vehicles.spektrum.config import SpektrumConfig
from agents.vehicles.spektrum.controls import FlightControls
from agents.vehicles.spektrum.frames import CHANNEL_NAMES
from agents.vehicles.spektrum.pump import (
    ControlTicker,
    FramePump,
    FrameStats,
    FrameTiming,
    FrameWriter,
    ReturnReader,
    timing_of,
)
from agents.vehicles.spektrum.report import FcReport, ReturnLineParser
from agents.vehicles.spektrum.vocabulary import (
    STICK_COMMANDS,
    TELEMETRY_TOPICS,
    spektrum_vocabulary,
)

logger = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------
# Commands
# --------------------------------------------------------------------------------------

#: :meth:`SpektrumAdapter.start` fails when no frame went out within this time.
START_TIMEOUT_S = 10.0
#: ``arm`` waits this long for the FC to report armed before giving up ...
ARM_WAIT_S = 1.0
#: ... or, with no telemetry (the real plane), holds the throttle at idle this long.
ARM_SETTLE_S = 0.25


class SpektrumAdapter(Adapter):
    """The Spektrum VTOL plane; see the module docstring and ``docs/vehicles/vtol.md``.

    After :meth:`start` frames are flowing: :attr:`controls` is the virtual transmitter
    and :attr:`writer` the frame writer (pump process or thread).
    """

    name = "spektrum"
    telemetry_labels = {
        "throttle": TopicInfo("Throttle (0 to 1)", decimals=2),
        # Servo positions as the receiver frames carry them (0..2047, centre 1024; 100 %
        # travel 342..1706), not pulse widths: no unit.
        "channels": TopicInfo("Receiver channels (position, 1024 = centre)", decimals=0),
        "frame_period_ms": TopicInfo("Receiver frame period", "ms", 1),
        "landing": TopicInfo("Landing", yes="landing", no="no"),
    }
    # A plane cannot stop in the air, nor find its way home over the receiver line.
    safe_action_words = dict.fromkeys(
        ("stop", "land", "return_to_home"), "hover in VTOL mode and land where it is"
    )

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.config = SpektrumConfig.from_options(options)
        self.controls = FlightControls(self.config)
        self.parser = ReturnLineParser()
        self.port: Any = None
        #: The frame writer: the pump process, or the thread fallback.
        self.writer: FramePump | FrameWriter | None = None
        self._ticker: ControlTicker | None = None
        self._reader: ReturnReader | None = None
        self._beat_task: asyncio.Task[None] | None = None

    # --- lifecycle ---------------------------------------------------------------------
    async def start(self) -> None:
        """Open the port, start the frame writer, the control and reader threads, and
        return once frames flow. Raises AdapterError ``hardware`` when the port cannot be
        opened or no frame can be written within START_TIMEOUT_S (everything started is
        closed again)."""
        cfg = self.config
        try:
            self.port = serial.serial_for_url(
                cfg.port,
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
                pump = FramePump(fd, cfg)
                self.writer = pump
                pump.start()
                self._ticker = ControlTicker(self.controls, pump, self.fc_report)
                self._ticker.start()
            else:
                self.writer = FrameWriter(self.port, self.controls, cfg, self.fc_report)
                self.writer.start()
        except OSError as exc:
            await self.close()
            raise AdapterError(f"cannot start the frame writer: {exc}", code="hardware") from exc
        self._reader = ReturnReader(self.port, self.parser)
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
        if isinstance(writer, FramePump):
            writer.publish(self.controls.tick(time.monotonic(), self.fc_report()))

    async def _beat(self) -> None:
        while True:
            self.controls.beat(time.monotonic())
            await asyncio.sleep(0.1)

    async def close(self) -> None:
        """Land first if the plane may be flying (up to ``close_timeout_s``), then stop
        the frame writer and the threads and close the port. Safe to call more than
        once.

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
        joinable: list[ControlTicker | ReturnReader | FramePump | FrameWriter | None]
        joinable = [self._ticker, self._reader, writer]
        for part in joinable:
            if part is not None:
                await asyncio.to_thread(part.join, 3.0)
        self.writer = self._ticker = self._reader = None
        if self.port is not None:
            with contextlib.suppress(Exception):
                self.port.close()
            self.port = None

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
        return spektrum_vocabulary(self.config)

    def telemetry_topics(self) -> list[str]:
        return list(TELEMETRY_TOPICS)

    def state(self) -> VehicleState:
        """Position, altitude, heading, speed and battery from fresh telemetry (None on
        the real plane without a sensor); armed and mode as commanded."""
        fc = self.fc_report()
        origin = self.config.origin
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
