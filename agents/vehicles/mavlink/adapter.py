"""The MAVLink adapter: the agent is the vehicle's ground station.

It talks MAVLink 2 (pymavlink) to an ArduPilot autopilot over UDP, TCP or a serial port
(:mod:`.link`), sends GCS heartbeats at 1 Hz, follows the autopilot's heartbeat (mode,
armed state) and the telemetry streams it asks for, and turns the users' commands into
MAVLink. Users and service developers never see MAVLink.

:class:`MavlinkAdapter` holds what every vehicle class shares; each class of vehicle
(:mod:`.classes`) has its own adapter for what differs: the copter flies
(:class:`~.copter.CopterAdapter`, ``docs/vehicles/quadcopter.md``), the rover and the
boat drive (:class:`~.rover.RoverAdapter`, ``docs/vehicles/boat.md``). Their modes,
commands, telemetry and safe actions are theirs; the link, the telemetry streams, the
GUIDED-mode bookkeeping, arming, going to a waypoint, the payload, the battery watch and
the fail-safe check are here.

GCS heartbeats are produced by the event loop on purpose: if the agent hangs, they stop
and the autopilot's own GCS fail-safe takes over.

Position: only while the autopilot has a fix (a 3D GPS fix, or an EKF with an absolute
position); before its first fix ArduPilot reports 0/0, which the agent reports as no
position (None) to users and to the platform.

Events (:meth:`~agents.vehicles.base.Adapter.emit`): ``autopilot_link_lost``,
``autopilot_link_restored``, ``low_battery``, ``autopilot_mode_changed`` (the autopilot
changed mode by itself, e.g. its own fail-safe), ``autopilot_warning`` (a STATUSTEXT of
severity WARNING or worse, but for one a class expects after what the agent did, e.g.
ArduRover's setpoint timeout after a stop; and an autopilot of another class than the
options say), ``safe_action_failed``, ``autopilot_fence_set`` (the autopilot's fence
set from a task's limits: see :mod:`.fence`).
"""

from __future__ import annotations

import abc
import asyncio
import contextlib
import logging
import math
import time
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from agents.telemetry import TopicInfo
from agents.vehicles.base import Adapter, AdapterError, Braking, CommandSpec, VehicleState
from agents.vehicles.mavlink.braking import kinematics_default, kinematics_read
from agents.vehicles.mavlink.config import MavlinkConfig
from agents.vehicles.mavlink.dialect import (
    DATA_STREAMS,
    EKF_POS_HORIZ_ABS,
    GPS_FIX_3D,
    GPS_FIX_WORDS,
    MASK_POSITION,
    MAV,
    command_name,
    statustext,
)
from agents.vehicles.mavlink.failsafe import failsafe_problems
from agents.vehicles.mavlink.fence import FenceState, fence_clear, fence_set, fence_words
from agents.vehicles.mavlink.link import AutopilotLink
from agents.vehicles.mavlink.mission import items_download, items_match, items_upload, plan_items
from agents.vehicles.mavlink.vocabulary import mavlink_vocabulary, telemetry_topics
from agents.vehicles.plan import MissionProgress, NativeMissions, PlanItem

logger = logging.getLogger(__name__)

#: The watch loop's period (s): a released key's setpoint ends within it.
WATCH_PERIOD_S = 0.05
#: A position older than this (s) is judged as this old: the streams come at 10 Hz.
MAX_POSITION_AGE_S = 1.0
#: From the agent's decision to the autopilot acting on it (s): a local link.
LINK_S = 0.05
#: How long :meth:`MavlinkAdapter.mission_adopt` waits for the autopilot to say which
#: mission item it flies (MISSION_CURRENT streams at 2 Hz or more).
ADOPT_WAIT_S = 3.0


@dataclass
class Telemetry:
    """The latest values from the autopilot's streams (event loop only)."""

    lat: float | None = None
    lon: float | None = None
    alt: float | None = None  # relative to home, m
    heading: float | None = None
    speed: float | None = None
    climb: float | None = None
    #: (north, east, up) m/s, from GLOBAL_POSITION_INT.
    velocity: tuple[float, float, float] | None = None
    battery: float | None = None
    satellites: int | None = None
    gps_fix: int | None = None
    ekf_flags: int | None = None
    landed_state: int | None = None
    home: tuple[float, float] | None = None
    mode: int | None = None
    armed: bool | None = None
    system_status: int | None = None
    mav_type: int | None = None
    position_at: float = 0.0
    boot_ms: int = 0
    #: The mission: the item the autopilot flies (MISSION_CURRENT), the state it says
    #: (MISSION_STATE_*, 0 when it does not say), the highest item it reached.
    mission_seq: int | None = None
    mission_state: int = 0
    mission_reached: int | None = None


class MavlinkAdapter(Adapter, NativeMissions, abc.ABC):
    """What every MAVLink vehicle class shares; see the module docstring. Subclasses
    implement the commands (:meth:`execute`), the safe actions, the envelope's answer,
    projections, :meth:`_busy` and :meth:`_stop_moving`."""

    name = "mavlink"
    telemetry_labels = {
        "autopilot_link": TopicInfo("Autopilot link", yes="up", no="lost"),
        "ekf_ok": TopicInfo("Position estimate", yes="healthy", no="not healthy"),
    }

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.config = MavlinkConfig.from_options(options)
        self.vehicle_class = self.config.vehicle_class
        self.link = AutopilotLink(self.config, on_message=self._dispatch)
        self.link.on_sent = self._sent
        self.t = Telemetry()
        self._tasks: list[asyncio.Task[None]] = []
        self._last_heartbeat: float | None = None
        self._first_heartbeat = asyncio.Event()
        self._link_reported_lost = False
        self._streams_requested_at = 0.0
        self._started_at = time.monotonic()
        # Who put the autopilot in its current mode: "user", "failsafe" (the agent's
        # safe action), "low_battery", or "autopilot" (a change we did not ask for).
        self._mode_owner = "autopilot"
        self._expected_mode: int | None = None
        # Until then, heartbeats contradicting a change the autopilot just acknowledged
        # are stale (sent before it) and ignored.
        self._optimistic_until = 0.0
        self._requesting_streams = False
        #: Until when the user's last movement setpoint holds (None: not moving).
        self._moving_until: float | None = None
        self._low_battery_handled = False
        self._class_warned = False
        self._background: set[asyncio.Task[Any]] = set()
        self._warned_at: dict[str, float] = {}
        #: Which name the autopilot has for its GCS system id (``MAV_GCS_SYSID`` or
        #: ``SYSID_MYGCS``), once :meth:`check_failsafe_params` found out; else None.
        self.gcs_sysid_param: str | None = None
        #: The autopilot's fence the agent set for the task, and what it replaced.
        self._fence = FenceState()
        self._fence_lock = asyncio.Lock()
        #: The plan uploaded by :meth:`mission_upload`: its size, and the plan index of
        #: each mission item after home (None: nothing uploaded).
        self._plan_size: int | None = None
        self._plan_index: list[int] = []
        #: A safe action was performed and no command came since (see :meth:`close`).
        self.safe_action_done = False
        #: How the vehicle brakes: the firmware's defaults until the autopilot's own
        #: limits are read at start (see :mod:`.braking`).
        self.kinematics = kinematics_default(self.vehicle_class, self.config)

    # --- the link's figures, for diagnostics and tests -----------------------------------
    @property
    def conn(self) -> Any:
        return self.link.conn

    @property
    def target(self) -> tuple[int, int] | None:
        return self.link.target

    @property
    def link_ok(self) -> bool:
        return self.link.ok

    @property
    def bad_frames(self) -> int:
        return self.link.bad_frames

    @property
    def stats(self) -> dict[str, int]:
        return self.link.stats

    @property
    def texts(self) -> deque[tuple[float, int, str]]:
        """The autopilot's recent STATUSTEXTs: (monotonic time, severity, text)."""
        return self.link.texts

    def local_port(self) -> int | None:
        """The local UDP/TCP port of the link (for tests and the simulator), or None."""
        return self.link.local_port()

    # --- lifecycle ---------------------------------------------------------------------
    async def start(self) -> None:
        """Open the link, start the heartbeats and the watch, wait up to
        ``connect_timeout_s`` for the autopilot's first heartbeat and ask for the
        telemetry streams.

        An autopilot that does not answer in time is not an error (it may boot later):
        the link is reported ``lost`` until it does. Raises AdapterError ``hardware``
        when the port cannot be opened.
        """
        try:
            await self.link.open()
        except (OSError, ValueError, RuntimeError) as exc:
            await self.close()
            raise AdapterError(f"cannot open the MAVLink link: {exc}", code="hardware") from exc
        self._tasks = [
            asyncio.create_task(self._heartbeats(), name="mavlink-heartbeats"),
            asyncio.create_task(self._watch(), name="mavlink-watch"),
        ]
        try:
            await self._wait_first_heartbeat(self.config.connect_timeout_s)
        except Exception:
            await self.close()
            raise
        if self._first_heartbeat.is_set():
            # In the background: on a slow radio link ten requests take a while, and
            # commands need not wait for them.
            self._spawn(self._request_streams())
            self._spawn(self._read_kinematics())

    async def _read_kinematics(self) -> None:
        self.kinematics = await kinematics_read(self.link, self.vehicle_class, self.config)

    def braking(self) -> Braking:
        """How the vehicle stops now, for the gate and the envelope (see
        :mod:`.braking`): the autopilot's deceleration and jerk, after the age of the
        position they judge on and the way to the autopilot; a movement's key let go,
        its setpoint goes on for ``setpoint_hold_s`` (and the watch's period) first."""
        age = time.monotonic() - self.t.position_at if self.t.position_at else MAX_POSITION_AGE_S
        reaction = min(max(age, 0.0), MAX_POSITION_AGE_S) + LINK_S
        vertical = self.kinematics.vertical
        return Braking(
            horizontal=self.kinematics.horizontal.stopping(reaction),
            vertical=None if vertical is None else vertical.stopping(reaction),
            hold_s=self.config.setpoint_hold_s + WATCH_PERIOD_S,
        )

    async def _wait_first_heartbeat(self, wait_s: float) -> None:
        try:
            async with asyncio.timeout(wait_s):
                await self._first_heartbeat.wait()
        except TimeoutError:
            logger.warning(
                "mavlink: no autopilot heartbeat on %s after %.0f s; waiting on",
                self.config.connection,
                wait_s,
            )
            self._link_reported_lost = True
            self.emit("autopilot_link_lost", {"silent_s": round(wait_s, 1)})

    async def close(self) -> None:
        """Leave the vehicle safe (``close_action`` while it is flying or under way and
        reachable, unless a safe action, such as the task's fail-safe on the agent's
        shutdown, was performed since the last command: that one stands), then stop the
        loops and close the link. Idempotent."""
        if (
            self.link.conn is not None
            and self.config.close_action != "none"
            and not self.safe_action_done
            and self.link.ok
            and self._busy()
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
        await self.link.close()

    # --- receiving (event loop) ----------------------------------------------------------
    def _sent(self, at: float, frame: bytes) -> None:
        """A message the link sent the autopilot: into the raw stream too."""
        if self.on_raw is not None:
            self.on_raw(at, frame)

    def _dispatch(self, msg: Any) -> None:
        """One message from the autopilot (the link already took its answers)."""
        if self.on_raw is not None:
            self.on_raw(time.time(), bytes(msg.get_msgbuf()))
        kind = msg.get_type()
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "HEARTBEAT":
            self._on_heartbeat(msg, source)
            return
        if self.link.target is None or source != self.link.target:
            return  # another component (camera, gimbal, another GCS): not ours
        t = self.t
        if kind == "GLOBAL_POSITION_INT":
            # Before its first fix ArduPilot sends the location it starts with, 0/0:
            # that is no position, and neither users nor matching may take it for one.
            if self._has_fix() and (msg.lat, msg.lon) != (0, 0):
                t.lat, t.lon = msg.lat / 1e7, msg.lon / 1e7
            else:
                t.lat = t.lon = None
            t.alt = msg.relative_alt / 1000.0
            t.speed = math.hypot(msg.vx, msg.vy) / 100.0
            t.climb = -msg.vz / 100.0
            t.velocity = (msg.vx / 100.0, msg.vy / 100.0, t.climb)
            if msg.hdg != 65535 and t.heading is None:
                t.heading = msg.hdg / 100.0
            t.position_at = time.monotonic()
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
        elif kind == "STATUSTEXT":
            self._on_text(msg)
        elif kind == "MISSION_CURRENT":
            t.mission_seq = int(msg.seq)
            t.mission_state = int(getattr(msg, "mission_state", 0) or 0)
        elif kind == "MISSION_ITEM_REACHED":
            t.mission_reached = max(int(msg.seq), t.mission_reached or 0)

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
        if self.link.target is None:
            # The first autopilot we hear: not a GCS, not a component without autopilot.
            if msg.type == MAV.MAV_TYPE_GCS or msg.autopilot == MAV.MAV_AUTOPILOT_INVALID:
                return
            self.link.target = source
            logger.info("mavlink: autopilot is system %d component %d", *source)
        if source != self.link.target:
            return
        now = time.monotonic()
        self._last_heartbeat = now
        self._first_heartbeat.set()
        t = self.t
        t.system_status = int(msg.system_status)
        t.mav_type = int(msg.type)
        self._check_class(t.mav_type)
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
                self._stop_moving()
                self.emit(
                    "autopilot_mode_changed",
                    {"mode": self.mode_name(mode), "previous": self.mode_name(previous)},
                )
        if not t.armed:
            self._stop_moving()
        if not self.link.ok:
            self.link.ok = True
            if self._link_reported_lost:
                self._link_reported_lost = False
                logger.warning("mavlink: autopilot link restored")
                self.emit("autopilot_link_restored", {})
                self._spawn(self._request_streams())

    def _check_class(self, mav_type: int) -> None:
        """An autopilot of another class than the options say: its modes mean other
        things, so say so (once) rather than fly a boat with a copter's mode numbers."""
        if self._class_warned or mav_type in self.vehicle_class.mav_types:
            return
        self._class_warned = True
        text = (
            f"the autopilot reports MAV_TYPE {mav_type}, not a {self.vehicle_class.name} "
            f"({self.vehicle_class.firmware}): check the vehicle_class option"
        )
        logger.error("mavlink: %s", text)
        self.emit("autopilot_warning", {"severity": int(MAV.MAV_SEVERITY_ERROR), "text": text})

    def _on_text(self, msg: Any) -> None:
        severity, text = int(msg.severity), statustext(msg)
        if self._expected_text(text):
            logger.debug("mavlink: autopilot says %r, as expected", text)
            return
        now = time.monotonic()
        # The same warning at most every 5 s: autopilots repeat pre-arm texts.
        if severity <= MAV.MAV_SEVERITY_WARNING and now - self._warned_at.get(text, -1e9) > 5.0:
            self._warned_at[text] = now
            self.emit("autopilot_warning", {"severity": severity, "text": text})

    def _expected_text(self, text: str) -> bool:
        """Whether the autopilot's ``text`` is the expected consequence of what the
        agent did, not news for the platform. Default: none is."""
        return False

    # --- background loops ------------------------------------------------------------------
    async def _heartbeats(self) -> None:
        """GCS heartbeat at 1 Hz (from the loop on purpose, see the module docstring)."""
        while True:
            self.link.send(
                MAV.MAVLink_heartbeat_message(
                    MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, MAV.MAV_STATE_ACTIVE, 3
                )
            )
            await asyncio.sleep(1.0)

    async def _watch(self) -> None:
        """20 Hz: autopilot link timeout, the movement-setpoint hold, stale streams."""
        while True:
            await asyncio.sleep(0.05)
            try:
                self._watch_once(time.monotonic())
            except Exception:
                logger.exception("mavlink watch loop iteration failed")

    def _watch_once(self, now: float) -> None:
        last = self._last_heartbeat
        if self.link.ok and last is not None and now - last > self.config.heartbeat_timeout_s:
            self.link.ok = False
            self._link_reported_lost = True
            self._moving_until = None
            logger.warning("mavlink: no heartbeat from the autopilot for %.1f s", now - last)
            self.emit("autopilot_link_lost", {"silent_s": round(now - last, 1)})
            self.link.lost()
        self._tick(now)
        if (
            self.link.ok
            and self._streams_requested_at
            and not self._requesting_streams
            and now - max(self.t.position_at, self._streams_requested_at) > 5.0
        ):
            logger.warning("mavlink: no position for 5 s; asking for the streams again")
            self._spawn(self._request_streams())

    def _tick(self, now: float) -> None:
        """Every watch loop iteration (20 Hz): a class's setpoint hold. Default: none."""

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
                await self.link.command_long(
                    MAV.MAV_CMD_SET_MESSAGE_INTERVAL,
                    (msg_id, 1e6 / hz if hz > 0 else -1),
                    ack_wait_s=1.5,
                )
            except AdapterError as exc:
                refused += 1
                logger.debug("mavlink: stream %s: %s", name, exc)
        if refused == len(rates):
            logger.warning("mavlink: SET_MESSAGE_INTERVAL refused; using REQUEST_DATA_STREAM")
            target = self.link.target_or_default()
            for stream_id, names in DATA_STREAMS:
                hz = max(rates.get(n, 1.0) for n in names)
                self.link.send(
                    MAV.MAVLink_request_data_stream_message(
                        target[0], target[1], stream_id, max(1, round(hz)), 1
                    )
                )

    # --- the vehicle's state -----------------------------------------------------------
    def mode_name(self, mode: int | None) -> str | None:
        """``GUIDED`` for the autopilot's mode number (None: not known yet)."""
        return self.vehicle_class.mode_name(mode)

    def _mode(self, name: str) -> int:
        """The autopilot's number of mode ``name``."""
        return self.vehicle_class.mode_number(name)

    def state(self) -> VehicleState:
        t = self.t
        return VehicleState(
            lat=t.lat,
            lon=t.lon,
            alt=t.alt if self.vehicle_class.flies else None,
            heading_deg=t.heading,
            speed_mps=t.speed,
            battery=t.battery,
            armed=t.armed,
            mode=self.mode_name(t.mode),
            home=t.home,
            velocity=t.velocity,
        )

    def telemetry_topics(self) -> list[str]:
        return telemetry_topics(self.vehicle_class)

    def _telemetry_common(self) -> dict[str, Any]:
        """The topics every class has; None until the autopilot sent them. ``location``
        (like :meth:`state`'s lat/lon, which the platform hears) is None while the
        autopilot has no fix: ArduPilot's 0/0 before its first fix is no position."""
        t = self.t
        ekf_ok = None
        if t.ekf_flags is not None:
            needed = 0x1 | 0x2 | 0x8 | 0x10  # attitude, horizontal velocity, alt, pos abs
            ekf_ok = t.ekf_flags & needed == needed
        return {
            "battery_level": None if t.battery is None else round(t.battery, 1),
            "location": None
            if t.lat is None or t.lon is None
            else {"lat": round(t.lat, 7), "lon": round(t.lon, 7)},
            "speed": None if t.speed is None else round(t.speed, 2),
            "heading": None if t.heading is None else round(t.heading, 1),
            "is_armed": t.armed,
            "number_of_gps_satellites": t.satellites,
            "autopilot_link": "ok" if self.link.ok else "lost",
            "gps_fix": None if t.gps_fix is None else GPS_FIX_WORDS.get(t.gps_fix, str(t.gps_fix)),
            "ekf_ok": ekf_ok,
        }

    def commands(self) -> list[CommandSpec]:
        return mavlink_vocabulary(self.config)

    @abc.abstractmethod
    def _busy(self) -> bool:
        """Whether the vehicle is out doing something a safe action should end (flying;
        armed and under way)."""

    @abc.abstractmethod
    def _stop_moving(self) -> None:
        """Forget the user's movement setpoints (the autopilot took over, or disarmed)."""

    # --- acting, shared --------------------------------------------------------------------
    def _require_link(self, what: str) -> None:
        if self.link.conn is None:
            raise AdapterError(
                f"the {self.vehicle_class.name}'s link is not open", code="not_ready"
            )
        self.link.require(what)

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
        # armed vehicle would wait for sticks nobody holds.
        await self._set_mode(self._mode("GUIDED"), owner="user")
        await self.link.command_long(MAV.MAV_CMD_COMPONENT_ARM_DISARM, (1,))
        self._assume(armed=True)

    async def _disarm_now(self) -> None:
        await self.link.command_long(MAV.MAV_CMD_COMPONENT_ARM_DISARM, (0,))
        self._assume(armed=False)

    async def _reposition(self, lat: float, lon: float, alt: float) -> None:
        """Go to a position in GUIDED (the caller made sure of GUIDED): DO_REPOSITION
        (COMMAND_INT, relative altitude) with no speed of its own, else, from an
        autopilot that does not know it, SET_POSITION_TARGET_GLOBAL_INT (no ACK exists
        for it)."""
        try:
            await self.link.command_int(
                MAV.MAV_CMD_DO_REPOSITION,
                MAV.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                (-1, MAV.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, math.nan),
                lat,
                lon,
                alt,
            )
        except AdapterError as exc:
            if "unsupported" not in str(exc):
                raise
            target = self.link.target_or_default()
            self.link.send(
                MAV.MAVLink_set_position_target_global_int_message(
                    self.link.boot_ms(self._started_at), target[0], target[1],
                    MAV.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, MASK_POSITION,
                    int(lat * 1e7), int(lon * 1e7), alt, 0, 0, 0, 0, 0, 0, 0, 0,
                )
            )  # fmt: skip
        self._moving_until = None

    async def _go_to_position(
        self, lat: float, lon: float, alt: float, *, speed: float | None
    ) -> None:
        """Go to a position at ``speed`` (None: the autopilot's cruise speed), in the
        order ArduPilot takes it: DO_REPOSITION first, then DO_CHANGE_SPEED. ArduRover
        refuses a speed (DO_CHANGE_SPEED, or DO_REPOSITION's own) unless GUIDED already
        drives to a position, and ArduCopter ignores DO_REPOSITION's and forgets one
        sent before it when GUIDED starts flying to a position. A refused speed leaves
        the vehicle holding where it is, not on its way at its cruise speed, and raises
        the refusal (AdapterError)."""
        await self._reposition(lat, lon, alt)
        if not speed:
            return
        try:
            await self._change_speed(speed)
        except AdapterError:
            t = self.t
            if t.lat is not None and t.lon is not None:
                with contextlib.suppress(AdapterError):
                    await self._reposition(t.lat, t.lon, t.alt or alt)
            raise

    async def _change_speed(self, speed: float) -> None:
        """DO_CHANGE_SPEED (ground speed): the autopilot's speed for the position it is
        going to (and, in RTL, for its return). FAILED where the mode takes none (see
        :meth:`_go_to_position`)."""
        await self.link.command_long(MAV.MAV_CMD_DO_CHANGE_SPEED, (1, speed, -1, 0))

    async def _release_payload(self) -> None:
        payload = self.config.payload or {}
        if payload.get("method") == "servo":
            await self.link.command_long(
                MAV.MAV_CMD_DO_SET_SERVO, (int(payload["servo"]), int(payload["pwm"]))
            )
        else:
            await self.link.command_long(MAV.MAV_CMD_DO_GRIPPER, (1, MAV.GRIPPER_ACTION_RELEASE))

    async def _command_mode(self, command: int, mode: int, *, owner: str) -> None:
        """A MAV_CMD that switches the autopilot to ``mode`` (NAV_LAND, RTL) by itself."""
        self._moving_until = None
        if not self.t.armed:
            return  # disarmed: already down, already home
        self._expected_mode = mode
        await self.link.command_long(command, ())
        self._mode_owner = owner
        self._assume(mode=mode)

    async def _set_mode(self, mode: int, *, owner: str) -> None:
        if self.t.mode == mode:
            self._mode_owner = owner
            return
        self._expected_mode = mode
        await self.link.command_long(
            MAV.MAV_CMD_DO_SET_MODE,
            (MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode),
            label=f"{command_name(MAV.MAV_CMD_DO_SET_MODE)} ({self.mode_name(mode)})",
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

    async def _try_in_turn(self, action: str, steps: list[Any]) -> None:
        """Await each step (a coroutine factory) until one is accepted; if none is, log
        and report ``safe_action_failed`` with every refusal."""
        errors = []
        for step in steps:
            try:
                await step()
                return
            except AdapterError as exc:
                errors.append(str(exc))
        logger.error("mavlink: safe action %s failed: %s", action, "; ".join(errors))
        self.emit("safe_action_failed", {"action": action, "reason": "; ".join(errors)})

    # --- the battery -------------------------------------------------------------------
    def _returning(self) -> bool:
        """Whether the autopilot brings the vehicle home or down by itself already."""
        names = {"RTL", "SMART_RTL", "LAND"}
        return self.mode_name(self.t.mode) in names

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
        action = "return_to_home" if self._busy() and not self._returning() else "none"
        logger.warning("mavlink: battery %.0f%% < %g%%: %s", battery, threshold, action)
        self.emit("low_battery", {"battery": battery, "threshold": threshold, "action": action})
        if action == "return_to_home":
            self._spawn(self._low_battery_return())

    async def _low_battery_return(self) -> None:
        self._stop_moving()
        try:
            await self._set_mode(self._mode("RTL"), owner="low_battery")
        except AdapterError as exc:
            logger.error("mavlink: low-battery RTL failed: %s", exc)
            self.emit("safe_action_failed", {"action": "return_to_home", "reason": str(exc)})

    # --- the autopilot's own fail-safe ---------------------------------------------------
    async def check_failsafe_params(
        self, expected_action: str, *, max_altitude_m: float | None = None
    ) -> list[str]:
        """Compare the autopilot's own GCS fail-safe with the task's ``expected_action``
        (``return_to_home``, ``land`` or ``stop``) and ceiling; meant for task start (see
        :func:`~.failsafe.failsafe_problems`). The name the autopilot has for its GCS
        system id is kept in :attr:`gcs_sysid_param`. Never raises."""
        problems, found = await failsafe_problems(
            self.link, self.vehicle_class, expected_action, max_altitude_m=max_altitude_m
        )
        if found is not None:
            self.gcs_sysid_param = found
        return problems

    async def fence_set(
        self,
        action: str,
        *,
        max_altitude_m: float | None = None,
        geofence_center: tuple[float, float] | None = None,
        geofence_radius_m: float | None = None,
    ) -> list[str]:
        """The autopilot's fence from the task's limits (see :mod:`.fence`); what was
        set goes to the platform as ``autopilot_fence_set``. Never raises."""
        try:
            # One at a time: a task's end and the next one's start may overlap.
            async with self._fence_lock:
                values, problems = await fence_set(
                    self.link, self.vehicle_class, action,
                    max_altitude_m=max_altitude_m, geofence_center=geofence_center,
                    geofence_radius_m=geofence_radius_m, home=self.t.home, state=self._fence,
                )  # fmt: skip
        except Exception as exc:  # a fence half set is reported, never raised
            logger.exception("mavlink: setting the autopilot's fence failed")
            return [f"setting the autopilot's fence failed: {exc}"]
        if values and not problems:
            logger.info("mavlink: the autopilot's fence is %s", values)
            self.emit("autopilot_fence_set", fence_words(values))
        return problems

    async def fence_clear(self) -> list[str]:
        """Put the autopilot's fence back as it was before the task (see
        :mod:`.fence`). Never raises."""
        try:
            async with self._fence_lock:
                if not self._fence.previous and not self._fence.uploaded:
                    return []
                return await fence_clear(self.link, self._fence)
        except Exception as exc:
            logger.exception("mavlink: clearing the autopilot's fence failed")
            return [f"clearing the autopilot's fence failed: {exc}"]

    # --- the autopilot's own missions (AUTO) -------------------------------------------
    def native_missions(self) -> NativeMissions | None:
        """The autopilot's AUTO (see :mod:`.mission`), unless the options say
        ``native_missions: false``."""
        return self if self.config.native_missions else None

    async def mission_upload(self, items: Sequence[PlanItem]) -> None:
        """Upload ``items`` as the autopilot's mission (home first, see
        :func:`.mission.plan_items`). A vehicle flying a mission in AUTO is switched to
        GUIDED first, where it holds: ArduPilot writes an upload straight over the
        mission it flies. A refused or broken upload is cleared (MISSION_CLEAR_ALL:
        ArduPilot keeps what it got of it, which nobody must fly) and raises
        AdapterError naming the refusal."""
        self._require_link("uploading a mission")
        mission_items, plan_index = plan_items(
            items, home=self.t.home, payload=self.config.payload, flies=self.vehicle_class.flies
        )
        if self.mode_name(self.t.mode) == "AUTO":
            await self._set_mode(self._mode("GUIDED"), owner="user")
        self._plan_size = None
        try:
            await items_upload(
                self.link, MAV.MAV_MISSION_TYPE_MISSION, mission_items, what="mission"
            )
        except AdapterError:
            with contextlib.suppress(AdapterError):
                await items_upload(self.link, MAV.MAV_MISSION_TYPE_MISSION, [], what="mission")
            raise
        self._plan_size, self._plan_index = len(items), plan_index

    async def mission_start(self) -> None:
        """Fly the uploaded mission from its first item: DO_SET_MISSION_CURRENT 1
        (ArduPilot would otherwise resume an interrupted mission where it stopped,
        MIS_RESTART 0), then mode AUTO. ArduCopter arms in neither AUTO nor with a
        mission that does not start with a take-off, so it must be flying already; a
        rover or a boat must be armed.
        Raises AdapterError ``not_ready`` (nothing uploaded, not flying) or the
        autopilot's refusal."""
        self._require_link("starting the mission")
        if self._plan_size is None:
            raise AdapterError("no mission has been uploaded", code="not_ready")
        if not self._busy():
            what = "take off" if self.vehicle_class.flies else "arm"
            raise AdapterError(f"{what} before starting a mission", code="not_ready")
        await self.link.command_long(MAV.MAV_CMD_DO_SET_MISSION_CURRENT, (1, 0))
        self._stop_moving()
        await self._set_mode(self._mode("AUTO"), owner="mission")
        # What the autopilot said before its ACK was about the mission before (a
        # MISSION_CURRENT of a finished one still on its way would read as this one
        # done): only what comes after it counts. The link keeps the order.
        self.t.mission_seq = self.t.mission_reached = None
        self.t.mission_state = 0

    async def mission_adopt(self, items: Sequence[PlanItem]) -> bool:
        """Whether the autopilot flies ``items`` already, as a mission under way in AUTO:
        one this vehicle's agent uploaded and started before it restarted (a companion
        computer that rebooted mid-flight). The mission is read back item by item
        (:func:`.mission.items_download`) and compared with what :meth:`mission_upload`
        would make of ``items``; when they agree, :meth:`mission_progress` follows it from
        where the autopilot is, and nothing is uploaded or restarted.

        False, with nothing changed, when the vehicle is not flying a mission in AUTO
        (a finished mission is never adopted: the same plan may be another task's), the
        mission read back is another one, or the autopilot does not say where it is in
        it within :data:`ADOPT_WAIT_S`."""
        self._require_link("reading the mission back")
        t = self.t
        if self.mode_name(t.mode) != "AUTO":
            return False
        # An agent just started hears the streams a moment after the first heartbeat:
        # where the mission is (MISSION_CURRENT) and whether the vehicle is under way.
        deadline = time.monotonic() + ADOPT_WAIT_S
        while time.monotonic() < deadline:
            if t.mission_seq is not None and (t.landed_state is not None or t.alt is not None):
                break
            await asyncio.sleep(0.05)
        if t.mission_seq is None or t.mission_state == MAV.MISSION_STATE_COMPLETE:
            return False
        if not self._busy():
            return False
        planned, plan_index = plan_items(
            items, home=t.home, payload=self.config.payload, flies=self.vehicle_class.flies
        )
        stored = await items_download(self.link, MAV.MAV_MISSION_TYPE_MISSION, what="mission")
        if not items_match(stored, planned):
            logger.info("mavlink: the autopilot flies another mission: not adopted")
            return False
        if self.mode_name(t.mode) != "AUTO":
            return False  # left meanwhile (a fail-safe, another ground station)
        self._plan_size, self._plan_index = len(items), plan_index
        self._mode_owner = "mission"
        return True

    def mission_progress(self) -> MissionProgress:
        """Where the autopilot is in the uploaded plan (mission item ``s`` is the plan
        item it was made from); ``finished``: it says so (MISSION_STATE_COMPLETE), or
        it has landed and disarmed at the last item."""
        size, t = self._plan_size, self.t
        if size is None:
            return MissionProgress()

        def index(seq: int | None) -> int | None:
            if seq is None or not 1 <= seq <= len(self._plan_index):
                return None
            return self._plan_index[seq - 1]

        current = index(t.mission_seq)
        finished = t.mission_state == MAV.MISSION_STATE_COMPLETE or (
            current == size - 1 and t.armed is False
        )
        return MissionProgress(current, index(t.mission_reached), finished)

    async def read_param(self, name: str) -> float:
        """One autopilot parameter. Raises AdapterError ``timeout`` or ``autopilot_lost``."""
        return await self.link.read_param(name)
