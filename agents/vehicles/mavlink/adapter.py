"""Adapter for MAVLink multicopters (the paper's Navio2/ArduPilot quadcopter, 4.2.2).

The agent is the drone's ground station: it talks MAVLink 2 (pymavlink) to the
autopilot over UDP, TCP or a serial port, sends GCS heartbeats at 1 Hz, follows the
autopilot's heartbeat (ArduCopter mode, armed state) and the telemetry streams it asks
for, and turns the paper's Table 3 commands into MAVLink. Users and service developers
never see MAVLink. The full mapping, the safety behaviour and how to fly a real drone
are in ``docs/vehicles/quadcopter.md``; in short:

=====================  ===============================================================
arm / disarm           GUIDED first (arm only), MAV_CMD_COMPONENT_ARM_DISARM
take_off(altitude_m)   GUIDED, arm if needed, MAV_CMD_NAV_TAKEOFF
front/back/left/right  SET_POSITION_TARGET_LOCAL_NED, MAV_FRAME_BODY_OFFSET_NED,
up/down(speed_mps)     velocity only, yaw rate 0 (hold the heading)
rotate_left/right      MAV_CMD_CONDITION_YAW, relative, direction -1/+1
go_to_waypoint         MAV_CMD_DO_CHANGE_SPEED if speed_mps, then MAV_CMD_DO_REPOSITION
                       (COMMAND_INT, relative altitude)
land                   MAV_CMD_NAV_LAND
return_to_home         MAV_CMD_NAV_RETURN_TO_LAUNCH
stop                   zero velocity setpoint (hover) in GUIDED
release_payload        MAV_CMD_DO_GRIPPER or MAV_CMD_DO_SET_SERVO (``payload`` option)
=====================  ===============================================================

Confirmation: every MAV_CMD waits for its COMMAND_ACK (resent every ``resend_s`` until
``command_timeout_s``): ACCEPTED is the user's ok; any other result raises
:class:`AdapterError` ``autopilot_refused`` with the autopilot's words (the result and
the STATUSTEXT it sent with it); no answer raises ``timeout``. Velocity setpoints have
no ACK in MAVLink: their ack means "accepted by the agent and sent", after the agent
checked that the drone is flying in GUIDED (or switched it back to GUIDED, with an ACK,
from a hold/return the user asked for).

Threads: pymavlink I/O blocks, so a **receiver thread** reads the link and hands each
message to the event loop (``call_soon_threadsafe``), where all state lives, and a
**writer thread** sends what the loop queues. The event loop never touches the port.
GCS heartbeats are produced by the event loop on purpose: if the agent hangs, they stop
and the autopilot's own GCS fail-safe takes over.

Position: only while the autopilot has a fix (a 3D GPS fix, or an EKF with an absolute
position); before its first fix ArduCopter reports 0/0, which the agent reports as no
position (None) to users and to the platform.

Events: set :attr:`MavlinkAdapter.on_event` to ``callable(name, data)``; it is called on
the event loop thread and must not block. Names: ``autopilot_link_lost``,
``autopilot_link_restored``, ``low_battery``, ``autopilot_mode_changed`` (the autopilot
changed mode by itself, e.g. its own fail-safe), ``autopilot_warning`` (a STATUSTEXT of
severity WARNING or worse), ``safe_action_failed``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import queue
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

# pymavlink picks its wire protocol from the environment when first imported: MAVLink 2.
os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # type: ignore[import-untyped, unused-ignore]

from agents.geo import distance_m, local_offset_m, offset
from agents.vehicles.base import (
    Adapter,
    AdapterError,
    Breach,
    CommandSpec,
    Projection,
    VehicleState,
)
from agents.vehicles.mavlink.config import VELOCITY_FRAMES, MavlinkConfig
from agents.vehicles.mavlink.vocabulary import TELEMETRY_TOPICS, mavlink_vocabulary

mavutil.set_dialect("ardupilotmega")
#: The MAVLink module of the ArduPilot dialect (message classes and constants).
MAV: Any = mavutil.mavlink

logger = logging.getLogger(__name__)

#: ArduCopter flight modes: custom_mode number -> name (pymavlink's table).
COPTER_MODES: dict[int, str] = dict(mavutil.mode_mapping_acm)
GUIDED, LOITER, RTL, LAND, BRAKE, SMART_RTL, AUTO = 4, 5, 6, 9, 17, 21, 3
#: Modes in which the drone holds or flies on its own and the user may take it back by
#: moving, if the user (or a user-link fail-safe) put it there.
RESUMABLE_MODES = frozenset({LOITER, BRAKE, RTL, LAND, SMART_RTL, 16, 2})

#: COMMAND_ACK results in words.
RESULT_WORDS = {
    1: "temporarily rejected",
    2: "denied",
    3: "unsupported",
    4: "failed",
    5: "in progress",
    6: "cancelled",
    7: "accepted only as COMMAND_LONG",
    8: "accepted only as COMMAND_INT",
    9: "refused: unsupported frame",
}
#: What a result means when the autopilot gave no STATUSTEXT with it.
RESULT_HINTS = {
    1: "the autopilot cannot do it right now, e.g. pre-arm checks failed",
    2: "the autopilot does not allow it in its current state",
    3: "the autopilot does not implement it",
    4: "the autopilot tried and could not",
}

#: SET_POSITION_TARGET_LOCAL_NED type_mask: ignore position and acceleration (bits
#: 0-2, 6-8) and yaw (bit 10); use velocity and yaw rate. 0b010111000111 = 1479.
MASK_VELOCITY_YAW_RATE = 0b0000_0101_1100_0111
#: Velocity and a (relative, in a body frame) yaw; ignore yaw rate. 0b100111000111.
MASK_VELOCITY_YAW = 0b0000_1001_1100_0111
#: SET_POSITION_TARGET_GLOBAL_INT: position only.
MASK_POSITION = 0b0000_1101_1111_1000

#: The REQUEST_DATA_STREAM fallback for autopilots without SET_MESSAGE_INTERVAL:
#: (stream id, the messages in it), rate = the fastest of those messages.
DATA_STREAMS = (
    (2, ("SYS_STATUS", "GPS_RAW_INT", "EXTENDED_SYS_STATE")),  # EXTENDED_STATUS
    (6, ("GLOBAL_POSITION_INT",)),  # POSITION
    (10, ("ATTITUDE",)),  # EXTRA1
    (11, ("VFR_HUD",)),  # EXTRA2
    (12, ("BATTERY_STATUS", "EKF_STATUS_REPORT")),  # EXTRA3
)


#: FS_GCS_ENABLE values (ArduCopter 4.x) -> what the autopilot does on GCS loss.
FS_GCS_WORDS = {
    0: "disabled",
    1: "RTL",
    2: "RTL (or continue a mission)",
    3: "SmartRTL or RTL",
    4: "SmartRTL or LAND",
    5: "LAND",
    6: "DO_LAND_START or RTL",
    7: "BRAKE or LAND",
}
#: Which FS_GCS_ENABLE values agree with a task's fail-safe action.
FS_GCS_AGREES = {
    "return_to_home": frozenset({1, 2, 3, 4, 6}),
    "land": frozenset({5}),
    "stop": frozenset({7}),
}

#: The autopilot parameter naming the GCS its fail-safe follows, newest name first:
#: ArduPilot 4.7 renamed SYSID_MYGCS to MAV_GCS_SYSID (and added MAV_GCS_SYSID_HI, the
#: upper end of a range of GCS ids); an autopilot has one name or the other.
GCS_SYSID_PARAMS = ("MAV_GCS_SYSID", "SYSID_MYGCS")
GCS_SYSID_HI = "MAV_GCS_SYSID_HI"
#: GPS_RAW_INT fix_type from which the autopilot's position is a position (3D fix).
GPS_FIX_3D = 3
#: EKF_STATUS_REPORT flag: the EKF has an absolute horizontal position (a GPS fix, or
#: what stands in for one, e.g. an external navigation system).
EKF_POS_HORIZ_ABS = 0x10


def command_name(command: int) -> str:
    """``MAV_CMD_NAV_TAKEOFF`` for 22; the number if the dialect does not know it."""
    entry = MAV.enums["MAV_CMD"].get(command)
    return str(entry.name) if entry is not None else f"MAV_CMD {command}"


def mode_name(mode: int | None) -> str | None:
    if mode is None:
        return None
    return COPTER_MODES.get(mode, f"MODE_{mode}")


# --------------------------------------------------------------------------------------
# What the autopilot told us
# --------------------------------------------------------------------------------------


@dataclass
class _Telemetry:
    """The latest values from the autopilot's streams (event loop only)."""

    lat: float | None = None
    lon: float | None = None
    alt: float | None = None  # relative to home, m
    heading: float | None = None
    speed: float | None = None
    climb: float | None = None
    battery: float | None = None
    satellites: int | None = None
    gps_fix: int | None = None
    ekf_flags: int | None = None
    landed_state: int | None = None
    home: tuple[float, float] | None = None
    mode: int | None = None
    armed: bool | None = None
    system_status: int | None = None
    position_at: float = 0.0
    boot_ms: int = 0


@dataclass
class _Pending:
    """A command waiting for its COMMAND_ACK."""

    command: int
    future: asyncio.Future[Any]
    sent_at: float


# --------------------------------------------------------------------------------------
# The adapter
# --------------------------------------------------------------------------------------


class MavlinkAdapter(Adapter):
    """A MAVLink (ArduCopter) multicopter; see the module docstring."""

    name = "mavlink"

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.config = MavlinkConfig.from_options(options)
        self.conn: Any = None
        self.t = _Telemetry()
        self.target: tuple[int, int] | None = None
        if self.config.target_system is not None:
            self.target = (self.config.target_system, self.config.target_component or 1)
        #: Frames pymavlink could not decode (bad CRC, garbage) and unknown message ids.
        self.bad_frames = 0
        self.unknown_messages = 0
        self.send_errors = 0
        self.stats: dict[str, int] = {"acks": 0, "refusals": 0, "timeouts": 0, "setpoints": 0}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._out: queue.Queue[Any] = queue.Queue(maxsize=1000)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._tasks: list[asyncio.Task[None]] = []
        self._pending: dict[int, _Pending] = {}
        self._param_waiters: dict[str, list[asyncio.Future[float]]] = {}
        self._command_lock = asyncio.Lock()
        self._texts: deque[tuple[float, int, str]] = deque(maxlen=20)
        self._last_heartbeat: float | None = None
        self._first_heartbeat = asyncio.Event()
        self._link_ok = False
        self._link_reported_lost = False
        self._streams_requested_at = 0.0
        self._started_at = time.monotonic()
        # Who put the autopilot in its current mode: "user", "failsafe" (the agent's
        # safe action), "low_battery", or "autopilot" (a change we did not ask for).
        self._mode_owner = "autopilot"
        self._expected_mode: int | None = None
        self._takeoff_at = 0.0
        # Until then, heartbeats contradicting a change the autopilot just acknowledged
        # are stale (sent before it) and ignored.
        self._optimistic_until = 0.0
        self._requesting_streams = False
        self._moving_until: float | None = None  # a velocity setpoint is active
        self._yaw_target: float | None = None
        self._yaw_deadline = 0.0
        self._low_battery_handled = False
        self._background: set[asyncio.Task[Any]] = set()
        self._warned_at: dict[str, float] = {}
        #: Which name the autopilot has for its GCS system id (``MAV_GCS_SYSID`` or
        #: ``SYSID_MYGCS``), once :meth:`check_failsafe_params` found out; else None.
        self.gcs_sysid_param: str | None = None

    # --- lifecycle ---------------------------------------------------------------------
    async def start(self) -> None:
        """Open the link, start the receiver and writer threads, heartbeats and
        watchdogs, wait up to ``connect_timeout_s`` for the autopilot's first heartbeat
        and ask for the telemetry streams.

        An autopilot that does not answer in time is not an error (it may boot later):
        the link is reported ``lost`` until it does. Raises AdapterError ``hardware``
        when the port cannot be opened.
        """
        self._loop = asyncio.get_running_loop()
        cfg = self.config
        try:
            self.conn = await asyncio.to_thread(self._open, cfg.connection)
        except (OSError, ValueError, RuntimeError) as exc:
            await self.close()
            raise AdapterError(f"cannot open the MAVLink link: {exc}", code="hardware") from exc
        self._threads = [
            threading.Thread(target=self._receive, name="mavlink-receive", daemon=True),
            threading.Thread(target=self._write, name="mavlink-write", daemon=True),
        ]
        for thread in self._threads:
            thread.start()
        self._tasks = [
            asyncio.create_task(self._heartbeats(), name="mavlink-heartbeats"),
            asyncio.create_task(self._watch(), name="mavlink-watch"),
        ]
        try:
            await self._wait_first_heartbeat(cfg.connect_timeout_s)
        except Exception:
            await self.close()
            raise
        if self._first_heartbeat.is_set():
            # In the background: on a slow radio link ten requests take a while, and
            # commands need not wait for them.
            self._spawn(self._request_streams())

    def _open(self, connection: str) -> Any:
        conn = mavutil.mavlink_connection(
            connection,
            baud=self.config.baud,
            source_system=self.config.source_system,
            source_component=self.config.source_component,
            dialect="ardupilotmega",
            autoreconnect=True,
        )
        # Undecodable frames become BAD_DATA messages instead of exceptions.
        conn.mav.robust_parsing = True
        return conn

    def local_port(self) -> int | None:
        """The local UDP/TCP port of the link (for tests and the simulator), or None."""
        port = getattr(self.conn, "port", None)
        if port is None or not hasattr(port, "getsockname"):
            return None
        with contextlib.suppress(OSError):
            return int(port.getsockname()[1])
        return None

    async def _wait_first_heartbeat(self, wait_s: float) -> None:
        deadline = time.monotonic() + wait_s
        while not self._first_heartbeat.is_set():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                logger.warning(
                    "mavlink: no autopilot heartbeat on %s after %.0f s; waiting on",
                    self.config.connection,
                    wait_s,
                )
                self._link_reported_lost = True
                self.emit("autopilot_link_lost", {"silent_s": round(wait_s, 1)})
                return
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._first_heartbeat.wait(), min(remaining, 0.2))

    async def close(self) -> None:
        """Leave the drone safe (``close_action`` if it is flying and reachable), then
        stop the loops and threads and close the link. Idempotent."""
        if (
            self.conn is not None
            and self.config.close_action != "none"
            and self._link_ok
            and self._in_air()
        ):
            await self.safe_action(self.config.close_action)
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._tasks = []
        for task in list(self._background):
            task.cancel()
        self._stop.set()
        with contextlib.suppress(queue.Full):
            self._out.put_nowait(None)
        for thread in self._threads:
            if thread.is_alive():
                await asyncio.to_thread(thread.join, 2.0)
        self._threads = []
        if self.conn is not None:
            with contextlib.suppress(Exception):
                self.conn.close()
            self.conn = None
        for pending in self._pending.values():
            if not pending.future.done():
                pending.future.cancel()
        self._pending.clear()

    # --- threads -------------------------------------------------------------------------
    def _receive(self) -> None:
        """Receiver thread: read messages and hand them to the event loop."""
        loop = self._loop
        assert loop is not None
        while not self._stop.is_set():
            conn = self.conn
            if conn is None:
                return
            try:
                conn.mav.robust_parsing = True
                msg = conn.recv_match(blocking=True, timeout=0.2)
            except Exception as exc:
                # pymavlink drops what it cannot decode; anything else (a TCP reset, a
                # serial port pulled) must not end the thread.
                if self._stop.is_set():
                    return
                self.bad_frames += 1
                logger.debug("mavlink: receive error: %s", exc)
                time.sleep(0.05)
                continue
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "BAD_DATA":
                self.bad_frames += 1
                continue
            if kind.startswith("UNKNOWN"):
                self.unknown_messages += 1
                continue
            try:
                loop.call_soon_threadsafe(self._handle, msg)
            except RuntimeError:  # the loop is closed: we are shutting down
                return

    def _write(self) -> None:
        """Writer thread: send what the event loop queued (None stops it)."""
        while not self._stop.is_set():
            try:
                msg = self._out.get(timeout=0.5)
            except queue.Empty:
                continue
            if msg is None:
                return
            conn = self.conn
            if conn is None:
                return
            try:
                conn.mav.send(msg)
            except Exception as exc:  # a dropped TCP peer, a serial write timeout
                self.send_errors += 1
                logger.debug("mavlink: send failed: %s", exc)

    def _send(self, msg: Any) -> None:
        try:
            self._out.put_nowait(msg)
        except queue.Full:
            self.send_errors += 1
            logger.warning("mavlink: send queue full, message dropped")

    # --- receiving (event loop) ----------------------------------------------------------
    def _handle(self, msg: Any) -> None:
        """One message from the receiver thread. Never raises."""
        try:
            self._dispatch(msg)
        except Exception:
            logger.exception("mavlink: error handling %s", msg.get_type())

    def _dispatch(self, msg: Any) -> None:
        kind = msg.get_type()
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "HEARTBEAT":
            self._on_heartbeat(msg, source)
            return
        if self.target is None or source != self.target:
            return  # another component (camera, gimbal, another GCS): not ours
        now = time.monotonic()
        t = self.t
        if kind == "GLOBAL_POSITION_INT":
            # Before its first fix ArduCopter sends the location it starts with, 0/0:
            # that is no position, and neither users nor matching may take it for one.
            if self._has_fix() and (msg.lat, msg.lon) != (0, 0):
                t.lat, t.lon = msg.lat / 1e7, msg.lon / 1e7
            else:
                t.lat = t.lon = None
            t.alt = msg.relative_alt / 1000.0
            t.speed = math.hypot(msg.vx, msg.vy) / 100.0
            t.climb = -msg.vz / 100.0
            if msg.hdg != 65535 and t.heading is None:
                t.heading = msg.hdg / 100.0
            t.position_at = now
            if msg.time_boot_ms + 10_000 < t.boot_ms:
                logger.warning("mavlink: the autopilot rebooted; asking for streams again")
                self._spawn(self._request_streams())
            t.boot_ms = msg.time_boot_ms
        elif kind == "ATTITUDE":
            t.heading = math.degrees(msg.yaw) % 360.0
        elif kind == "VFR_HUD":
            if t.speed is None:
                t.speed = float(msg.groundspeed)
            if t.heading is None:
                t.heading = float(msg.heading) % 360.0
        elif kind == "SYS_STATUS":
            if msg.battery_remaining >= 0:
                t.battery = float(msg.battery_remaining)
                self._check_battery()
        elif kind == "BATTERY_STATUS":
            if msg.battery_remaining >= 0 and msg.id == 0:
                t.battery = float(msg.battery_remaining)
                self._check_battery()
        elif kind == "GPS_RAW_INT":
            t.gps_fix = int(msg.fix_type)
            t.satellites = None if msg.satellites_visible == 255 else int(msg.satellites_visible)
            self._forget_position_without_fix()
        elif kind == "EXTENDED_SYS_STATE":
            t.landed_state = int(msg.landed_state)
        elif kind == "EKF_STATUS_REPORT":
            t.ekf_flags = int(msg.flags)
            self._forget_position_without_fix()
        elif kind == "HOME_POSITION":
            t.home = (msg.latitude / 1e7, msg.longitude / 1e7)
        elif kind == "COMMAND_ACK":
            self._on_ack(msg)
        elif kind == "STATUSTEXT":
            self._on_text(msg)
        elif kind == "PARAM_VALUE":
            name = _param_name(msg.param_id)
            for future in self._param_waiters.pop(name, []):
                if not future.done():
                    future.set_result(float(msg.param_value))

    def _has_fix(self) -> bool:
        """Whether the autopilot knows where it is: a 3D GPS fix (GPS_RAW_INT), or an
        EKF with an absolute horizontal position (a fix or what stands in for one).
        Neither reported yet: no."""
        t = self.t
        if t.gps_fix is not None and t.gps_fix >= GPS_FIX_3D:
            return True
        return t.ekf_flags is not None and bool(t.ekf_flags & EKF_POS_HORIZ_ABS)

    def _forget_position_without_fix(self) -> None:
        if not self._has_fix():
            self.t.lat = self.t.lon = None

    def _on_heartbeat(self, msg: Any, source: tuple[int, int]) -> None:
        if self.target is None:
            # The first autopilot we hear: not a GCS, not a component without autopilot.
            if msg.type == MAV.MAV_TYPE_GCS or msg.autopilot == MAV.MAV_AUTOPILOT_INVALID:
                return
            self.target = source
            logger.info("mavlink: autopilot is system %d component %d", *source)
        if source != self.target:
            return
        now = time.monotonic()
        self._last_heartbeat = now
        self._first_heartbeat.set()
        t = self.t
        t.system_status = int(msg.system_status)
        armed = bool(msg.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED)
        custom = bool(msg.base_mode & MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
        mode = int(msg.custom_mode) if custom else None
        if now < self._optimistic_until and (armed != t.armed or mode != t.mode):
            # A heartbeat sent before the autopilot acknowledged our change: stale.
            return
        t.armed = armed
        if mode is not None and mode != t.mode:
            previous = t.mode
            t.mode = mode
            if mode == self._expected_mode:
                self._expected_mode = None
            elif previous is not None:
                self._mode_owner = "autopilot"
                self._moving_until = None
                self.emit(
                    "autopilot_mode_changed",
                    {"mode": mode_name(mode), "previous": mode_name(previous)},
                )
        if not t.armed:
            self._moving_until = None
            self._yaw_target = None
        if not self._link_ok:
            self._link_ok = True
            if self._link_reported_lost:
                self._link_reported_lost = False
                logger.warning("mavlink: autopilot link restored")
                self.emit("autopilot_link_restored", {})
                self._spawn(self._request_streams())

    def _on_ack(self, msg: Any) -> None:
        target_system = getattr(msg, "target_system", 0)
        if target_system not in (0, self.config.source_system):
            return  # an answer to another ground station on the same link
        pending = self._pending.get(int(msg.command))
        if pending is not None and not pending.future.done():
            pending.future.set_result(msg)

    def _on_text(self, msg: Any) -> None:
        text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode("ascii", "replace")
        text = text.split("\x00", 1)[0].strip()
        now = time.monotonic()
        self._texts.append((now, int(msg.severity), text))
        # The same warning at most every 5 s: autopilots repeat pre-arm texts.
        if msg.severity <= MAV.MAV_SEVERITY_WARNING and now - self._warned_at.get(text, -1e9) > 5.0:
            self._warned_at[text] = now
            self.emit("autopilot_warning", {"severity": int(msg.severity), "text": text})

    # --- background loops ------------------------------------------------------------------
    async def _heartbeats(self) -> None:
        """GCS heartbeat at 1 Hz (from the loop on purpose, see the module docstring)."""
        while True:
            self._send(
                MAV.MAVLink_heartbeat_message(
                    MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, MAV.MAV_STATE_ACTIVE, 3
                )
            )
            await asyncio.sleep(1.0)

    async def _watch(self) -> None:
        """20 Hz: autopilot link timeout, the velocity-setpoint hold, stale streams."""
        while True:
            await asyncio.sleep(0.05)
            try:
                self._watch_once(time.monotonic())
            except Exception:
                logger.exception("mavlink watch loop iteration failed")

    def _watch_once(self, now: float) -> None:
        last = self._last_heartbeat
        if self._link_ok and last is not None and now - last > self.config.heartbeat_timeout_s:
            self._link_ok = False
            self._link_reported_lost = True
            self._moving_until = None
            logger.warning("mavlink: no heartbeat from the autopilot for %.1f s", now - last)
            self.emit("autopilot_link_lost", {"silent_s": round(now - last, 1)})
            for pending in self._pending.values():
                if not pending.future.done():
                    pending.future.set_exception(self._lost_error(command_name(pending.command)))
        if self._moving_until is not None and now > self._moving_until:
            # The user stopped repeating the command (key released, browser gone): hover
            # now rather than when the autopilot's own setpoint timeout (3 s) ends it.
            self._moving_until = None
            if self._link_ok and self.t.mode == GUIDED:
                self._send_velocity(0.0, 0.0, 0.0)
        if (
            self._link_ok
            and self._streams_requested_at
            and not self._requesting_streams
            and now - max(self.t.position_at, self._streams_requested_at) > 5.0
        ):
            logger.warning("mavlink: no position for 5 s; asking for the streams again")
            self._spawn(self._request_streams())

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._background.add(task)
        task.add_done_callback(self._background.discard)

    async def _request_streams(self) -> None:
        """Ask for every telemetry stream at its rate (SET_MESSAGE_INTERVAL), falling back
        to REQUEST_DATA_STREAM for an autopilot that refuses or ignores it."""
        if self._requesting_streams:
            return
        self._requesting_streams = True
        try:
            await self._request_streams_once()
        finally:
            self._requesting_streams = False
            self._streams_requested_at = time.monotonic()

    async def _request_streams_once(self) -> None:
        refused = 0
        rates = self.config.stream_rates_hz
        for name, hz in rates.items():
            msg_id = getattr(MAV, f"MAVLINK_MSG_ID_{name}")
            try:
                await self._command_long(
                    MAV.MAV_CMD_SET_MESSAGE_INTERVAL,
                    (msg_id, 1e6 / hz if hz > 0 else -1),
                    ack_wait_s=1.5,
                )
            except AdapterError as exc:
                refused += 1
                logger.debug("mavlink: stream %s: %s", name, exc)
        if refused == len(rates):
            logger.warning("mavlink: SET_MESSAGE_INTERVAL refused; using REQUEST_DATA_STREAM")
            target = self.target or (1, 1)
            for stream_id, names in DATA_STREAMS:
                hz = max(rates.get(n, 1.0) for n in names)
                self._send(
                    MAV.MAVLink_request_data_stream_message(
                        target[0], target[1], stream_id, max(1, round(hz)), 1
                    )
                )

    # --- the autopilot's state ---------------------------------------------------------
    @property
    def link_ok(self) -> bool:
        return self._link_ok

    def _in_air(self) -> bool:
        t = self.t
        if not t.armed:
            return False
        if time.monotonic() - self._takeoff_at < 5.0:
            return True  # the autopilot accepted a takeoff; its streams lag behind
        if t.landed_state in (2, 3, 4):  # IN_AIR, TAKEOFF, LANDING
            return True
        if t.landed_state == 1:  # ON_GROUND
            return False
        return t.alt is not None and t.alt > 0.5

    def state(self) -> VehicleState:
        t = self.t
        return VehicleState(
            lat=t.lat,
            lon=t.lon,
            alt=t.alt,
            heading_deg=t.heading,
            speed_mps=t.speed,
            battery=t.battery,
            armed=t.armed,
            mode=mode_name(t.mode),
            home=t.home,
        )

    def telemetry_topics(self) -> list[str]:
        return list(TELEMETRY_TOPICS)

    def telemetry(self) -> dict[str, Any]:
        """Every topic of :data:`TELEMETRY_TOPICS`; None until the autopilot sent it.
        ``location`` (like :meth:`state`'s lat/lon, which the platform hears) is None
        while the autopilot has no fix: ArduCopter's 0/0 before its first fix is no
        position."""
        t = self.t
        fix = {0: "none", 1: "none", 2: "2D", 3: "3D", 4: "DGPS", 5: "RTK float", 6: "RTK"}
        ekf_ok = None
        if t.ekf_flags is not None:
            needed = 0x1 | 0x2 | 0x8 | 0x10  # attitude, horizontal velocity, alt, pos abs
            ekf_ok = t.ekf_flags & needed == needed
        return {
            "battery_level": None if t.battery is None else round(t.battery, 1),
            "altitude": None if t.alt is None else round(t.alt, 2),
            "location": None
            if t.lat is None or t.lon is None
            else {"lat": round(t.lat, 7), "lon": round(t.lon, 7)},
            "speed": None if t.speed is None else round(t.speed, 2),
            "heading": None if t.heading is None else round(t.heading, 1),
            "flight_mode": mode_name(t.mode),
            "is_armed": t.armed,
            "number_of_gps_satellites": t.satellites,
            "autopilot_link": "ok" if self._link_ok else "lost",
            "gps_fix": None if t.gps_fix is None else fix.get(t.gps_fix, str(t.gps_fix)),
            "ekf_ok": ekf_ok,
            "in_air": self._in_air() if t.armed is not None else None,
        }

    # --- vocabulary --------------------------------------------------------------------
    def commands(self) -> list[CommandSpec]:
        return mavlink_vocabulary(self.config)

    # --- the envelope ------------------------------------------------------------------
    def project(self, name: str, args: Mapping[str, Any]) -> Projection | None:
        """Where a command takes the drone, for the gate's ceiling and geofence checks:
        a movement ``setpoint_hold_s`` (1 s) ahead at the commanded speed (body axes
        turned by the heading), the target altitude of ``take_off``, the waypoint of
        ``go_to_waypoint``; None for the rest."""
        t = self.t
        if name == "take_off":
            return Projection(lat=t.lat, lon=t.lon, alt=float(args.get("altitude_m", 0)))
        if name == "go_to_waypoint":
            return Projection(
                lat=float(args["lat"]), lon=float(args["lon"]), alt=float(args["alt_m"])
            )
        body = _BODY_AXES.get(name)
        if body is None:
            return None
        distance = float(args.get("speed_mps", self.config.move_speed_mps))
        distance *= self.config.setpoint_hold_s
        forward, right, up = (axis * distance for axis in body)
        alt = None if t.alt is None else max(0.0, t.alt + up)
        if t.lat is None or t.lon is None or t.heading is None or (forward == right == 0):
            return Projection(alt=alt)
        north, east = _body_to_ned(forward, right, t.heading)
        lat, lon = offset((t.lat, t.lon), north, east)
        return Projection(lat=lat, lon=lon, alt=alt)

    # --- acting ------------------------------------------------------------------------
    async def execute(self, name: str, args: Mapping[str, Any]) -> None:
        """Carry out a checked command; see the module docstring for the mapping.

        Raises AdapterError: ``autopilot_lost`` (no heartbeat), ``autopilot_refused`` (a
        COMMAND_ACK other than ACCEPTED, with its words), ``timeout`` (no COMMAND_ACK in
        ``command_timeout_s``), ``not_flying`` / ``in_air`` / ``low_battery`` /
        ``autopilot_mode`` (checked here before anything is sent), ``not_ready``,
        ``unknown_command``.
        """
        if self.conn is None:
            raise AdapterError("the drone's link is not open", code="not_ready")
        self._require_link(name)
        body = _BODY_AXES.get(name)
        if body is not None:
            speed = float(args.get("speed_mps", self.config.move_speed_mps))
            await self._move(name, *(axis * speed for axis in body))
        elif name in ("rotate_left", "rotate_right"):
            await self._rotate(name, float(args.get("angle_deg", self.config.rotate_default_deg)))
        elif name == "take_off":
            await self._take_off(float(args.get("altitude_m", self.config.takeoff_default_m)))
        elif name == "arm":
            await self._arm()
        elif name == "disarm":
            await self._disarm()
        elif name == "land":
            await self._land_or_return(MAV.MAV_CMD_NAV_LAND, LAND, owner="user")
        elif name == "return_to_home":
            await self._land_or_return(MAV.MAV_CMD_NAV_RETURN_TO_LAUNCH, RTL, owner="user")
        elif name == "go_to_waypoint":
            speed = min(float(args.get("speed_mps") or 0), self.config.max_speed_mps)
            await self._go_to(
                float(args["lat"]), float(args["lon"]), float(args["alt_m"]), speed=speed or None
            )
        elif name == "stop":
            # Stop moving and turning: yaw rate 0 also ends a rotation under way.
            self._moving_until = None
            self._yaw_target = None
            if self.t.mode == GUIDED and self._in_air():
                self._send_velocity(0.0, 0.0, 0.0)
        elif name == "release_payload" and self.config.payload is not None:
            await self._release_payload()
        else:
            raise AdapterError(f"{name!r} is not a command of this drone", code="unknown_command")

    def _lost_error(self, what: str) -> AdapterError:
        return AdapterError(
            f"no heartbeat from the autopilot for over {self.config.heartbeat_timeout_s:g} s: "
            f"{what} is refused",
            code="autopilot_lost",
        )

    def _require_link(self, what: str) -> None:
        if not self._link_ok:
            raise self._lost_error(what)

    def _check_battery_for(self, what: str) -> None:
        battery = self.t.battery
        if battery is not None and battery < self.config.low_battery_pct:
            raise AdapterError(
                f"battery at {battery:.0f}% (below {self.config.low_battery_pct:g}%): "
                f"{what} is refused",
                code="low_battery",
            )

    async def _arm(self) -> None:
        if self.t.armed:
            return
        self._check_battery_for("arming")
        # The agent is the only pilot: arm in GUIDED, never in a manual mode where an
        # armed copter would wait for sticks nobody holds.
        await self._set_mode(GUIDED, owner="user")
        await self._command_long(MAV.MAV_CMD_COMPONENT_ARM_DISARM, (1,))
        self._assume(armed=True)

    async def _disarm(self) -> None:
        if self.t.armed is False:
            return
        if self._in_air():
            raise AdapterError("the drone is flying: land first, then disarm", code="in_air")
        await self._command_long(MAV.MAV_CMD_COMPONENT_ARM_DISARM, (0,))
        self._assume(armed=False)

    async def _take_off(self, altitude: float) -> None:
        if self._in_air():
            alt = self.t.alt
            where = f" at {alt:.1f} m" if alt is not None else ""
            raise AdapterError(f"already flying{where}: use up and down", code="in_air")
        self._check_battery_for("take-off")
        await self._set_mode(GUIDED, owner="user")
        if not self.t.armed:
            await self._command_long(MAV.MAV_CMD_COMPONENT_ARM_DISARM, (1,))
            self._assume(armed=True)
        await self._command_long(MAV.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, math.nan, 0, 0, altitude))
        self._takeoff_at = time.monotonic()

    async def _ensure_guided_flight(self, what: str) -> None:
        """Refuse unless the drone flies in GUIDED; take it back to GUIDED from a hold,
        return or landing that the user (or the user-link fail-safe) started."""
        t = self.t
        if not t.armed or not self._in_air():
            raise AdapterError(
                f"the drone is on the ground: take off first ({what})", code="not_flying"
            )
        if t.mode == GUIDED:
            return
        mode = mode_name(t.mode)
        if self._mode_owner == "low_battery":
            battery = "" if t.battery is None else f" (battery {t.battery:.0f}%)"
            raise AdapterError(
                f"low battery{battery}: the drone is returning home; {what} is refused",
                code="low_battery",
            )
        if t.mode in RESUMABLE_MODES and self._mode_owner in ("user", "failsafe"):
            await self._set_mode(GUIDED, owner="user")
            return
        raise AdapterError(
            f"the autopilot is in {mode} on its own (e.g. its own fail-safe): {what} is refused",
            code="autopilot_mode",
        )

    async def _move(self, name: str, forward: float, right: float, up: float) -> None:
        await self._ensure_guided_flight(name)
        self._send_velocity(forward, right, up)
        self._moving_until = time.monotonic() + self.config.setpoint_hold_s

    def _send_velocity(self, forward: float, right: float, up: float) -> None:
        """A body-frame velocity setpoint. Yaw: rate 0 (hold the heading), or the rest
        of a rotation still under way (relative yaw), never "ignored": ArduCopter then
        falls back to WP_YAW_BEHAVIOR and turns the nose into the direction of travel,
        which in a body frame sends "right" round in circles."""
        target = self._target()
        yaw_left = self._yaw_remaining()
        mask, yaw = MASK_VELOCITY_YAW_RATE, 0.0
        if yaw_left is not None:
            mask, yaw = MASK_VELOCITY_YAW, math.radians(yaw_left)
        boot_ms = int((time.monotonic() - self._started_at) * 1000) & 0xFFFFFFFF
        self._send(
            MAV.MAVLink_set_position_target_local_ned_message(
                boot_ms, target[0], target[1], VELOCITY_FRAMES[self.config.velocity_frame],
                mask, 0.0, 0.0, 0.0, forward, right, -up, 0.0, 0.0, 0.0, yaw, 0.0,
            )
        )  # fmt: skip
        self.stats["setpoints"] += 1

    def _yaw_remaining(self) -> float | None:
        if self._yaw_target is None or self.t.heading is None:
            return None
        left = _wrap180(self._yaw_target - self.t.heading)
        if abs(left) < 2.0 or time.monotonic() > self._yaw_deadline:
            self._yaw_target = None
            return None
        return left

    async def _rotate(self, name: str, angle: float) -> None:
        """CONDITION_YAW, relative. A held key repeats the command, and the autopilot
        adds a relative yaw to the rotation still under way: sending the full angle
        each time would pile targets up and keep the drone turning long after the key
        is released. So the target is kept ``angle`` ahead of the current heading: only
        the shortfall is sent (nothing, when the target is already far enough ahead)."""
        await self._ensure_guided_flight(name)
        direction = -1 if name == "rotate_left" else 1
        heading = self.t.heading
        pending = self._yaw_remaining() or 0.0
        delta = direction * angle - pending
        rate = self.config.rotate_rate_deg_s
        if abs(delta) >= 1.0:
            turn = 1 if delta > 0 else -1
            await self._command_long(MAV.MAV_CMD_CONDITION_YAW, (abs(delta), rate, turn, 1))
        if heading is not None:
            self._yaw_target = (heading + direction * angle) % 360.0
            self._yaw_deadline = time.monotonic() + angle / rate + 3.0

    async def _go_to(
        self, lat: float, lon: float, alt: float, *, speed: float | None = None
    ) -> None:
        await self._ensure_guided_flight("go_to_waypoint")
        if speed:
            # ArduCopter flies guided targets at WPNAV_SPEED and ignores DO_REPOSITION's
            # speed field: DO_CHANGE_SPEED (ground speed) sets it for this and later legs.
            await self._command_long(MAV.MAV_CMD_DO_CHANGE_SPEED, (1, speed, -1, 0))
        await self._reposition(lat, lon, alt, speed=speed)

    async def _reposition(
        self, lat: float, lon: float, alt: float, *, speed: float | None = None
    ) -> None:
        """Fly to a position in GUIDED (the caller made sure of GUIDED)."""
        try:
            await self._command_int(
                MAV.MAV_CMD_DO_REPOSITION,
                MAV.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                (speed or -1, MAV.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, math.nan),
                lat,
                lon,
                alt,
            )
        except AdapterError as exc:
            if "unsupported" not in str(exc):
                raise
            # Older ArduCopter: the position target message (no ACK exists for it).
            target = self._target()
            boot_ms = int((time.monotonic() - self._started_at) * 1000) & 0xFFFFFFFF
            self._send(
                MAV.MAVLink_set_position_target_global_int_message(
                    boot_ms, target[0], target[1], MAV.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                    MASK_POSITION, int(lat * 1e7), int(lon * 1e7), alt,
                    0, 0, 0, 0, 0, 0, 0, 0,
                )
            )  # fmt: skip
        self._moving_until = None

    async def _release_payload(self) -> None:
        payload = self.config.payload or {}
        if payload.get("method") == "servo":
            await self._command_long(
                MAV.MAV_CMD_DO_SET_SERVO, (int(payload["servo"]), int(payload["pwm"]))
            )
        else:
            await self._command_long(MAV.MAV_CMD_DO_GRIPPER, (1, MAV.GRIPPER_ACTION_RELEASE))

    async def _land_or_return(self, command: int, mode: int, *, owner: str) -> None:
        self._moving_until = None
        if not self.t.armed:
            return  # on the ground and disarmed: already landed, already home
        self._expected_mode = mode
        await self._command_long(command, ())
        self._mode_owner = owner
        self._assume(mode=mode)

    async def _set_mode(self, mode: int, *, owner: str) -> None:
        if self.t.mode == mode:
            self._mode_owner = owner
            return
        self._expected_mode = mode
        await self._command_long(
            MAV.MAV_CMD_DO_SET_MODE,
            (MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode),
            label=f"{command_name(MAV.MAV_CMD_DO_SET_MODE)} ({mode_name(mode)})",
        )
        self._mode_owner = owner
        self._assume(mode=mode)

    def _assume(self, *, mode: int | None = None, armed: bool | None = None) -> None:
        """Take an acknowledged change as done before the next heartbeat shows it."""
        if mode is not None:
            self.t.mode = mode
            self._expected_mode = None
        if armed is not None:
            self.t.armed = armed
        self._optimistic_until = time.monotonic() + 1.5

    # --- safety ------------------------------------------------------------------------
    async def safe_action(self, action: str) -> None:
        """Make the drone safe; never raises (a failure is logged and reported as the
        ``safe_action_failed`` event).

        ``return_to_home``: RTL (the autopilot climbs to RTL_ALT, flies home, lands and
        disarms), falling back to LAND; ``land``: LAND; ``stop``: hover (zero velocity),
        then BRAKE, falling back to LOITER, then LAND. Armed on the ground: disarm.
        Disarmed: nothing to do. Without a link to the autopilot nothing can be sent:
        the autopilot's own GCS fail-safe (see :meth:`check_failsafe_params`) acts.
        """
        self._moving_until = None
        self._yaw_target = None
        try:
            if not self._link_ok:
                logger.error("mavlink: safe action %s impossible: no autopilot link", action)
                self.emit(
                    "safe_action_failed",
                    {"action": action, "reason": "no link to the autopilot"},
                )
                return
            if not self.t.armed:
                return
            if not self._in_air():
                await self._command_long(MAV.MAV_CMD_COMPONENT_ARM_DISARM, (0,))
                self._assume(armed=False)
                return
            steps: list[Callable[[], Any]]
            if action == "land":
                steps = [lambda: self._set_mode(LAND, owner="failsafe")]
            elif action == "stop":
                if self.t.mode == GUIDED:
                    self._send_velocity(0.0, 0.0, 0.0)
                steps = [
                    lambda: self._set_mode(BRAKE, owner="failsafe"),
                    lambda: self._set_mode(LOITER, owner="failsafe"),
                    lambda: self._set_mode(LAND, owner="failsafe"),
                ]
            else:
                steps = [
                    lambda: self._set_mode(RTL, owner="failsafe"),
                    lambda: self._command_long(MAV.MAV_CMD_NAV_RETURN_TO_LAUNCH, ()),
                    lambda: self._set_mode(LAND, owner="failsafe"),
                ]
            errors = []
            for step in steps:
                try:
                    await step()
                    return
                except AdapterError as exc:
                    errors.append(str(exc))
            logger.error("mavlink: safe action %s failed: %s", action, "; ".join(errors))
            self.emit("safe_action_failed", {"action": action, "reason": "; ".join(errors)})
        except Exception:
            logger.exception("mavlink: safe action %s failed", action)
            self.emit("safe_action_failed", {"action": action, "reason": "internal error"})

    async def envelope_recover(self, breach: Breach) -> str:
        """Bring the drone back inside a limit it crossed, whatever crossed it.

        * altitude: a position target right here, ``breach.target`` high (GUIDED):
          the climb stops and the drone descends below the ceiling and holds; in RTL
          (its climb to RTL_ALT crossed the ceiling) LAND instead, as ArduCopter's
          own fence does when breached during a return; in LAND nothing to do;
        * geofence: a position target ``breach.target`` from the centre on the line to
          where it is, at its altitude (GUIDED); nothing in LAND or RTL (on its way
          down or home);
        * speed: a zero velocity setpoint if the user's movement is under way, and
          DO_CHANGE_SPEED to ``breach.target`` (the autopilot's cruise speed for
          positions, returns and later legs).

        Flying is what the user's own commands see afterwards, in GUIDED. Raises
        AdapterError when the autopilot refuses (the hub reports it as the action).
        """
        t = self.t
        moving = self._moving_until is not None
        if not self._link_ok:
            return "none: no link to the autopilot"
        if not t.armed or not self._in_air():
            return "none: not flying"
        if breach.limit == "speed":
            if moving and t.mode == GUIDED:
                self._moving_until = None
                self._send_velocity(0.0, 0.0, 0.0)
            await self._command_long(MAV.MAV_CMD_DO_CHANGE_SPEED, (1, breach.target, -1, 0))
            return f"slow down to {breach.target:.1f} m/s"
        if t.mode == LAND:
            return "none: landing"
        if t.mode in (RTL, SMART_RTL):
            if breach.limit == "geofence":
                return "none: returning home"
            owner = "low_battery" if self._mode_owner == "low_battery" else "failsafe"
            await self._set_mode(LAND, owner=owner)
            return "land: the return climbs above the ceiling"
        if t.lat is None or t.lon is None or t.alt is None:
            return "none: position unknown"
        lat, lon, alt = t.lat, t.lon, t.alt
        if breach.limit == "altitude":
            alt = breach.target
            action = f"descend to {alt:.1f} m and hold"
        else:
            centre = breach.centre or (lat, lon)
            out = distance_m(centre, (lat, lon))
            if out > 0:
                north, east = local_offset_m(centre, (lat, lon))
                share = max(0.0, breach.target) / out
                lat, lon = offset(centre, north * share, east * share)
            action = "fly back inside the geofence and hold"
        self._moving_until = None
        self._yaw_target = None
        if t.mode != GUIDED:
            await self._set_mode(GUIDED, owner="failsafe")
        await self._reposition(lat, lon, alt)
        return action

    async def neutral(self) -> None:
        """Hover: a zero velocity setpoint if the drone flies in GUIDED. Never raises."""
        self._moving_until = None
        if self._link_ok and self.t.mode == GUIDED and self._in_air():
            self._send_velocity(0.0, 0.0, 0.0)

    def _check_battery(self) -> None:
        battery = self.t.battery
        threshold = self.config.low_battery_pct
        if battery is None:
            return
        if battery >= threshold + 5.0:
            self._low_battery_handled = False  # a fresh battery: watch again
            return
        if battery >= threshold or self._low_battery_handled:
            return
        self._low_battery_handled = True
        flying = self._in_air()
        returning = self.t.mode in (RTL, LAND, SMART_RTL)
        action = "return_to_home" if flying and not returning else "none"
        logger.warning("mavlink: battery %.0f%% < %g%%: %s", battery, threshold, action)
        self.emit("low_battery", {"battery": battery, "threshold": threshold, "action": action})
        if action == "return_to_home":
            self._spawn(self._low_battery_return())

    async def _low_battery_return(self) -> None:
        self._moving_until = None
        try:
            await self._set_mode(RTL, owner="low_battery")
        except AdapterError as exc:
            logger.error("mavlink: low-battery RTL failed: %s", exc)
            self.emit("safe_action_failed", {"action": "return_to_home", "reason": str(exc)})

    async def check_failsafe_params(
        self, expected_action: str, *, max_altitude_m: float | None = None
    ) -> list[str]:
        """Compare the autopilot's own GCS fail-safe with the task's ``expected_action``
        (``return_to_home``, ``land`` or ``stop``); meant for task start.

        Reads FS_GCS_ENABLE, FS_GCS_TIMEOUT and the GCS system id (``MAV_GCS_SYSID``, with
        ``MAV_GCS_SYSID_HI``, on ArduPilot 4.7 and later, else ``SYSID_MYGCS``; the name
        found is kept in :attr:`gcs_sysid_param` and named in the answer), and RTL_ALT
        when ``max_altitude_m`` is given and the task returns home, with
        PARAM_REQUEST_READ, all at once. Returns the mismatches in words, [] when they
        agree. Never raises: a parameter the autopilot does not answer for is itself
        reported. On an autopilot with the older name it takes up to
        ``command_timeout_s``: ArduPilot does not answer for a name it lacks.
        """
        if not self._link_ok:
            return ["cannot check the autopilot's fail-safe: no link to the autopilot"]
        names = ["FS_GCS_ENABLE", "FS_GCS_TIMEOUT"]
        if max_altitude_m is not None and expected_action == "return_to_home":
            names.append("RTL_ALT")
        gcs_read = asyncio.ensure_future(self._read_gcs_sysid())
        answers = await asyncio.gather(*(self._read_or_problem(name) for name in names))
        values = dict(zip(names, answers, strict=True))
        gcs = await gcs_read
        problems = [value for value in values.values() if isinstance(value, str)]
        enable = values.get("FS_GCS_ENABLE")
        if isinstance(enable, float):
            code = int(enable)
            words = FS_GCS_WORDS.get(code, f"action {code}")
            if code == 0:
                problems.append(
                    f"the autopilot's GCS fail-safe is disabled (FS_GCS_ENABLE=0) but the task "
                    f"expects {expected_action}: if the agent stops, the drone keeps its last "
                    "command"
                )
            elif code not in FS_GCS_AGREES.get(expected_action, frozenset()):
                problems.append(
                    f"the autopilot's GCS fail-safe does {words} (FS_GCS_ENABLE={code}) but "
                    f"the task expects {expected_action}"
                )
        if isinstance(gcs, str):
            problems.append(gcs)
        else:
            name, low, high = gcs
            agent = self.config.source_system
            if high is not None and high >= low:
                if not low <= agent <= high:
                    problems.append(
                        f"the autopilot's GCS fail-safe follows systems {low}-{high} ({name}, "
                        f"{GCS_SYSID_HI}) but the agent is system {agent}: it would never see "
                        "the agent's heartbeats"
                    )
            elif low != agent:
                problems.append(
                    f"the autopilot's GCS fail-safe follows system {low} ({name}) but the agent "
                    f"is system {agent}: it would never see the agent's heartbeats"
                )
        rtl_alt = values.get("RTL_ALT")
        if (
            isinstance(rtl_alt, float)
            and max_altitude_m is not None
            and rtl_alt / 100.0 > max_altitude_m
        ):
            problems.append(
                f"RTL climbs to {rtl_alt / 100.0:g} m (RTL_ALT={rtl_alt:g} cm), above the "
                f"task's {max_altitude_m:g} m ceiling"
            )
        return problems

    async def _read_or_problem(self, name: str) -> float | str:
        """One parameter, or why it could not be read (in words)."""
        try:
            return await self.read_param(name)
        except AdapterError as exc:
            return str(exc)

    async def _read_gcs_sysid(self) -> tuple[str, int, int | None] | str:
        """(the name the autopilot has, its GCS system id, MAV_GCS_SYSID_HI or None), or
        why neither name could be read (in words). Both names are asked for at once, the
        newer first. ArduPilot answers reads in order and has only one of them, so once
        the older name answered the newer one gets one ``resend_s`` more (an autopilot
        with both, or a reordering link), then the older one counts."""
        loop = asyncio.get_running_loop()
        tasks = [asyncio.ensure_future(self.read_param(name)) for name in GCS_SYSID_PARAMS]
        try:
            pending: set[asyncio.Future[float]] = set(tasks)
            grace_until: float | None = None
            while pending:
                wait = None if grace_until is None else max(0.0, grace_until - loop.time())
                done, pending = await asyncio.wait(
                    pending, timeout=wait, return_when=asyncio.FIRST_COMPLETED
                )
                if not done:
                    break  # the newer name's grace is over
                answered = [t.done() and t.exception() is None for t in tasks]
                if answered[0] or (answered[1] and tasks[0].done()):
                    break
                if answered[1] and grace_until is None:
                    grace_until = loop.time() + self.config.resend_s
            for name, task in zip(GCS_SYSID_PARAMS, tasks, strict=True):
                if task.done() and task.exception() is None:
                    self.gcs_sysid_param = name
                    value = int(task.result())
                    logger.info("mavlink: the autopilot's GCS system id: %s=%d", name, value)
                    high = None
                    if name == "MAV_GCS_SYSID":
                        answer = await self._read_or_problem(GCS_SYSID_HI)
                        high = int(answer) if isinstance(answer, float) else None
                    return name, value, high
            errors = [t.exception() for t in tasks if t.done()]
            lost = [e for e in errors if isinstance(e, AdapterError) and e.code != "timeout"]
            if lost:
                return str(lost[0])
            return (
                f"the autopilot did not answer for parameter {' or '.join(GCS_SYSID_PARAMS)} "
                f"within {self.config.command_timeout_s:g} s"
            )
        finally:
            for task in tasks:
                if not task.done():
                    task.cancel()
                elif not task.cancelled():
                    task.exception()  # retrieved: a failed read is part of the answer

    async def read_param(self, name: str) -> float:
        """One autopilot parameter (PARAM_REQUEST_READ, resent until
        ``command_timeout_s``). Raises AdapterError ``timeout`` or ``autopilot_lost``."""
        self._require_link(f"reading {name}")
        loop = asyncio.get_running_loop()
        future: asyncio.Future[float] = loop.create_future()
        self._param_waiters.setdefault(name, []).append(future)
        target = self._target()
        deadline = time.monotonic() + self.config.command_timeout_s
        try:
            while True:
                self._send(
                    MAV.MAVLink_param_request_read_message(target[0], target[1], name.encode(), -1)
                )
                wait = min(self.config.resend_s, deadline - time.monotonic())
                try:
                    return await asyncio.wait_for(asyncio.shield(future), max(0.01, wait))
                except TimeoutError:
                    if time.monotonic() >= deadline:
                        raise AdapterError(
                            f"the autopilot did not answer for parameter {name} within "
                            f"{self.config.command_timeout_s:g} s",
                            code="timeout",
                        ) from None
        finally:
            waiters = self._param_waiters.get(name, [])
            if future in waiters:
                waiters.remove(future)

    # --- the command protocol ----------------------------------------------------------
    def _target(self) -> tuple[int, int]:
        return self.target or (self.config.target_system or 1, self.config.target_component or 1)

    async def _command_long(
        self,
        command: int,
        params: Sequence[float],
        *,
        ack_wait_s: float | None = None,
        label: str | None = None,
    ) -> Any:
        p = list(params) + [0.0] * (7 - len(params))
        target = self._target()

        def build(confirmation: int) -> Any:
            return MAV.MAVLink_command_long_message(target[0], target[1], command, confirmation, *p)

        return await self._transact(command, build, ack_wait_s=ack_wait_s, label=label)

    async def _command_int(
        self, command: int, frame: int, params: Sequence[float], lat: float, lon: float, z: float
    ) -> Any:
        p = list(params) + [0.0] * (4 - len(params))
        target = self._target()

        def build(_: int) -> Any:
            return MAV.MAVLink_command_int_message(
                target[0], target[1], frame, command, 0, 0, *p,
                round(lat * 1e7), round(lon * 1e7), z,
            )  # fmt: skip

        return await self._transact(command, build, ack_wait_s=None, label=None)

    async def _transact(
        self,
        command: int,
        build: Callable[[int], Any],
        *,
        ack_wait_s: float | None,
        label: str | None,
    ) -> Any:
        """Send a command, resend it until its COMMAND_ACK, and turn the ACK into the
        agent's answer (see the module docstring)."""
        what = label or command_name(command)
        self._require_link(what)
        loop = asyncio.get_running_loop()
        timeout = self.config.command_timeout_s if ack_wait_s is None else ack_wait_s
        async with self._command_lock:
            started = time.monotonic()
            deadline = started + timeout
            pending = _Pending(command, loop.create_future(), started)
            self._pending[command] = pending
            confirmation = 0
            try:
                self._send(build(confirmation))
                while True:
                    wait = min(self.config.resend_s, deadline - time.monotonic())
                    try:
                        ack = await asyncio.wait_for(
                            asyncio.shield(pending.future), max(0.01, wait)
                        )
                    except TimeoutError:
                        if time.monotonic() >= deadline:
                            self.stats["timeouts"] += 1
                            raise AdapterError(
                                f"the autopilot did not answer {what} within {timeout:g} s",
                                code="timeout",
                            ) from None
                        # Lost on the way, or its ACK was: MAVLink resends with the
                        # confirmation counter raised.
                        confirmation = min(255, confirmation + 1)
                        self._send(build(confirmation))
                        continue
                    if ack.result == MAV.MAV_RESULT_IN_PROGRESS:
                        pending.future = loop.create_future()
                        continue
                    break
            finally:
                self._pending.pop(command, None)
        self.stats["acks"] += 1
        if ack.result != MAV.MAV_RESULT_ACCEPTED:
            self.stats["refusals"] += 1
            raise AdapterError(
                self._refusal(what, int(ack.result), started), code="autopilot_refused"
            )
        return ack

    def _refusal(self, what: str, result: int, since: float) -> str:
        words = RESULT_WORDS.get(result, f"result {result}")
        texts = [text for at, _, text in self._texts if at >= since - 0.05]
        reason = "; ".join(dict.fromkeys(texts[-2:])) or RESULT_HINTS.get(result, "")
        return f"autopilot refused {what}: {words}" + (f" ({reason})" if reason else "")


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------

#: Movement commands as (forward, right, up) unit vectors in the body frame.
_BODY_AXES: dict[str, tuple[float, float, float]] = {
    "front": (1.0, 0.0, 0.0),
    "back": (-1.0, 0.0, 0.0),
    "left": (0.0, -1.0, 0.0),
    "right": (0.0, 1.0, 0.0),
    "up": (0.0, 0.0, 1.0),
    "down": (0.0, 0.0, -1.0),
}


def _body_to_ned(forward: float, right: float, heading_deg: float) -> tuple[float, float]:
    """(north, east) of a body-frame (forward, right) vector at ``heading_deg``."""
    h = math.radians(heading_deg)
    return (
        forward * math.cos(h) - right * math.sin(h),
        forward * math.sin(h) + right * math.cos(h),
    )


def _wrap180(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


def _param_name(raw: Any) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0].strip()


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port free right now (for tests that start a simulator themselves)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])
