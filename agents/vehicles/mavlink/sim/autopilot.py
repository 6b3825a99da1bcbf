"""An ArduPilot-like MAVLink autopilot for one simulated vehicle: the wire and the
protocol, apart from the vehicle models (:mod:`.copter`, :mod:`.boat`).

It speaks MAVLink 2 through pymavlink the way ArduPilot does for the command set the
IoUV agent uses (``docs/vehicles/quadcopter.md``, ``docs/vehicles/boat.md``):

* HEARTBEAT at 1 Hz: the vehicle's MAV_TYPE, ``MAV_AUTOPILOT_ARDUPILOTMEGA``, base_mode
  flags (custom mode enabled, guided, armed), ``custom_mode`` = the firmware's mode
  number, system_status (CRITICAL during a GCS fail-safe or on an empty battery);
* a COMMAND_ACK for every COMMAND_LONG/COMMAND_INT addressed to it (unknown commands:
  ``MAV_RESULT_UNSUPPORTED``), with a STATUSTEXT explaining a refusal first, as
  ArduPilot does. Here: arming, DO_SET_MODE / SET_MODE, the gripper and servos
  ("Gripper load released"), SET_MESSAGE_INTERVAL, GET_MESSAGE_INTERVAL,
  REQUEST_MESSAGE, REQUEST_AUTOPILOT_CAPABILITIES (AUTOPILOT_VERSION),
  GET_HOME_POSITION; the vehicle's own (take-off, landing, repositioning, speed...) go
  to the vehicle model, as do SET_POSITION_TARGET_LOCAL_NED and _GLOBAL_INT;
* telemetry streams from the start, every stream group at ``stream_rate_hz`` (1 Hz,
  the default of ArduPilot's stream-rate parameters on ArduPlane and ArduRover;
  ArduCopter ships 0), changed per group by REQUEST_DATA_STREAM and per message by
  SET_MESSAGE_INTERVAL (0: back to the group's rate);
* parameters (PARAM_REQUEST_READ / PARAM_REQUEST_LIST / PARAM_SET) of the firmware and
  release it plays (:mod:`.params`);
* a GPS that may take ``gps_fix_after_s`` seconds to get its fix;
* the GCS fail-safe's clock: the last heartbeat of the GCS (``SYSID_MYGCS``, or from 4.7
  ``MAV_GCS_SYSID``..``MAV_GCS_SYSID_HI``), after which silence the vehicle model
  acts (:meth:`~.vehicle.SimVehicle.gcs_failsafe`);
* the fence (:mod:`.fence`): its parameters, its upload, download and clearing with the
  mission protocol for ``MAV_MISSION_TYPE_FENCE``, its check at 25 Hz and ArduPilot's
  breach action, a FENCE_STATUS when its state changes;
* the mission (:mod:`.mission`): its upload, download and clearing with the mission
  protocol for ``MAV_MISSION_TYPE_MISSION`` (with ArduPilot's refusals and its 8 s
  upload timeout), MAV_CMD_DO_SET_MISSION_CURRENT, and while AUTO flies it (each
  vehicle's own: :mod:`.copter`, :mod:`.boat`) MISSION_CURRENT on every change (and
  in the EXTENDED_STATUS stream) and MISSION_ITEM_REACHED;
* TIMESYNC.

Time: ``speedup`` runs the vehicle's physics (and the delays measured in its time: RTL
loiter, disarm delay, battery drain) that many times faster than the wall clock.
Everything about the link stays on the wall clock: heartbeats, stream rates, setpoint
timeouts and the GCS fail-safe, because the peer sends at wall-clock rates; so does the
time to the first GPS fix, which is not flight.

Not modelled: rally points, RC input, wind, terrain, EKF variances,
signing.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from agents.vehicles.mavlink.dialect import MAV, mavutil, param_name
from agents.vehicles.mavlink.sim.boat import Boat
from agents.vehicles.mavlink.sim.copter import Copter
from agents.vehicles.mavlink.sim.fence import FenceTransfer, fence_breach_type
from agents.vehicles.mavlink.sim.messages import STREAMABLE, Clocks, heartbeat, message
from agents.vehicles.mavlink.sim.mission import MissionTransfer
from agents.vehicles.mavlink.sim.params import DEFAULT_FIRMWARE, FIRMWARES, firmware_params
from agents.vehicles.mavlink.sim.vehicle import CommandResult, PositionTarget, SimVehicle, wrap360

log = logging.getLogger(__name__)

#: The simulated vehicles by class name (``--vehicle-class``).
VEHICLES: Mapping[str, type[Copter] | type[Boat]] = {"copter": Copter, "boat": Boat}

#: REQUEST_DATA_STREAM stream ids -> the messages ArduPilot sends in them (those of
#: them this simulator has), as GCS_MAVLink_Parameters.cpp groups them.
DATA_STREAMS: dict[int, tuple[str, ...]] = {
    2: ("SYS_STATUS", "GPS_RAW_INT", "EXTENDED_SYS_STATE", "MISSION_CURRENT"),  # EXT_STATUS
    6: ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),  # POSITION
    10: ("ATTITUDE",),  # EXTRA1
    11: ("VFR_HUD",),  # EXTRA2
    12: ("BATTERY_STATUS", "EKF_STATUS_REPORT", "SYSTEM_TIME"),  # EXTRA3
}
DATA_STREAMS[0] = tuple(m for ms in DATA_STREAMS.values() for m in ms)  # ALL

#: What every stream group sends before a ground station asks for anything, in Hz:
#: ArduPilot's stream-rate parameters (SRn_EXT_STAT, SRn_POSITION, SRn_EXTRA1..3;
#: MAVn_* from 4.7) default to 1 Hz on ArduPlane, ArduRover and AntennaTracker, and to 0
#: on ArduCopter (libraries/GCS_MAVLink/GCS_MAVLink_Parameters.cpp). The simulator
#: streams by default so that any ground station shows telemetry at once; a rate of 0
#: is ArduCopter's own behaviour (nothing until asked).
DEFAULT_STREAM_RATE_HZ = 1.0
MAX_STREAM_HZ = 50.0
PHYSICS_HZ = 50.0
#: How often the fence is checked (ArduCopter: 25 Hz).
FENCE_HZ = 25.0
#: MAV_CMD_COMPONENT_ARM_DISARM's param 2 that forces a disarm.
FORCE_DISARM = 21196


@dataclass(frozen=True)
class SimOptions:
    """What a simulator runs with (its command line, :mod:`.cli`)."""

    address: str
    home: tuple[float, float]
    #: The vehicle: ``copter`` (ArduCopter) or ``boat`` (ArduRover, FRAME_CLASS 2).
    vehicle: str = "copter"
    home_alt_amsl: float = 50.0
    heading_deg: float = 0.0
    speedup: float = 1.0
    battery_pct: float = 100.0
    drain_pct_per_min: float = 5.0
    gps_fix: int = 3
    satellites: int = 12
    sysid: int = 1
    params: Mapping[str, float] = field(default_factory=dict)
    parent_pid: int | None = None
    #: Every stream group's rate until a GCS asks otherwise (ArduPilot's SRn_
    #: parameters, see :data:`DEFAULT_STREAM_RATE_HZ`); 0: only what is asked for.
    stream_rate_hz: float = DEFAULT_STREAM_RATE_HZ
    #: Wall-clock seconds from the start until the GPS has its fix (``gps_fix``).
    gps_fix_after_s: float = 0.0
    #: The simulated release, a key of :data:`~.params.FIRMWARES` (its parameter names).
    firmware: str = DEFAULT_FIRMWARE
    #: A boat's water current: (m/s, the direction it flows towards in degrees).
    current: tuple[float, float] = (0.0, 0.0)


def vehicle_create(options: SimOptions, params: dict[str, float]) -> SimVehicle:
    """The vehicle ``options`` name, at home, with the live parameter table ``params``."""
    common: dict[str, Any] = {
        "params": params,
        "home": options.home,
        "home_alt_amsl": options.home_alt_amsl,
        "yaw": wrap360(options.heading_deg),
        "battery_pct": options.battery_pct,
        "drain_pct_per_min": options.drain_pct_per_min,
        "gps_fix": options.gps_fix,
        "satellites": options.satellites,
    }
    if options.vehicle == "boat":
        speed, towards = options.current
        flow = math.radians(towards)
        return Boat(**common, current=(speed * math.cos(flow), speed * math.sin(flow)))
    return Copter(**common)


class Autopilot:
    """Serves one simulated vehicle on one MAVLink link (UDP, TCP or serial).

    Single-threaded: :meth:`run` polls the link, steps the physics at 50 Hz and sends
    heartbeats and the requested streams. :meth:`stop` (any thread or a signal handler)
    ends it. Bad input (bad CRC, garbage, unknown messages) is dropped and counted.
    Raises ValueError for options no simulated firmware has.
    """

    def __init__(self, options: SimOptions, *, clock: Callable[[], float] = time.monotonic):
        self.options = options
        self.clock = clock
        if options.firmware not in FIRMWARES:
            known = ", ".join(FIRMWARES)
            raise ValueError(f"unknown firmware {options.firmware!r}; one of {known}")
        if options.vehicle not in VEHICLES:
            raise ValueError(f"no simulated {options.vehicle!r}; one of {', '.join(VEHICLES)}")
        firmware = VEHICLES[options.vehicle].VEHICLE_CLASS.firmware
        #: This firmware's parameters: name -> (default, is_integer), in index order.
        self.param_table = firmware_params(options.firmware, options.vehicle)
        params = {name: float(default) for name, (default, _) in self.param_table.items()}
        params["MAV_SYSID" if "MAV_SYSID" in params else "SYSID_THISMAV"] = float(options.sysid)
        for name, value in options.params.items():
            if name not in self.param_table:
                raise ValueError(
                    f"unknown parameter {name!r} on {firmware} {options.firmware}; "
                    f"known: {', '.join(self.param_table)}"
                )
            params[name] = float(value)
        self.vehicle = vehicle_create(options, params)
        self.gps_fix_at: float | None = None  # wall time the GPS gets its fix, if later
        if options.gps_fix_after_s > 0 and options.gps_fix > 0:
            # A GPS still searching: connected (NO_FIX), no satellites used yet.
            self.vehicle.gps_fix, self.vehicle.satellites = 1, 0
            self.gps_fix_at = clock() + options.gps_fix_after_s
        self.conn: Any = None
        self.started = clock()
        self.intervals: dict[str, float] = {}  # message name -> seconds (wall)
        self.next_due: dict[str, float] = {}
        #: What SET_MESSAGE_INTERVAL's "default rate" (0) restores: the stream rates.
        self.default_intervals: dict[str, float] = {}
        #: Set by :meth:`stop`, never cleared: a SIGTERM that comes between READY and
        #: :meth:`run`'s first turn stops it all the same.
        self.stopping = False
        self.bad_frames = 0
        self.unknown_messages = 0
        self.gcs_last: float | None = None  # wall time of the last heartbeat of the GCS
        self.gcs_failsafe = False
        self.peers: dict[tuple[int, int], float] = {}
        self.fence_transfer = FenceTransfer(self.vehicle.fence, options.home)
        self.mission_transfer = MissionTransfer(self.vehicle.mission, options.home)
        self.next_fence_check = 0.0
        if options.stream_rate_hz > 0:
            for name in DATA_STREAMS[0]:
                interval = 1.0 / min(options.stream_rate_hz, MAX_STREAM_HZ)
                self.default_intervals[name] = interval
                self._stream(name, interval)

    # --- lifecycle --------------------------------------------------------------------
    def open(self) -> str:
        """Open the link; returns a description with the actual port (for udpin:...:0)."""
        self.conn = mavutil.mavlink_connection(
            self.options.address,
            source_system=self.options.sysid,
            source_component=MAV.MAV_COMP_ID_AUTOPILOT1,
            dialect="ardupilotmega",
            autoreconnect=True,
        )
        self.conn.mav.robust_parsing = True
        # The bound socket: a TCP server's listening one, else the link's own.
        port = getattr(self.conn, "listen", None) or getattr(self.conn, "port", None)
        address = self.options.address
        if port is not None and hasattr(port, "getsockname"):
            with contextlib.suppress(OSError):
                host, number = port.getsockname()[:2]
                if address.startswith(("udpin:", "udp:", "tcpin:")):
                    address = f"{address.split(':', 1)[0]}:{host}:{number}"
        return address

    def close(self) -> None:
        if self.conn is not None:
            with contextlib.suppress(Exception):
                self.conn.close()
            self.conn = None

    def stop(self, *_: Any) -> None:
        """Make :meth:`run` return (at once if it has not started); a signal handler."""
        self.stopping = True

    def run(self) -> None:
        """Serve until :meth:`stop` (or the parent process, if given, goes away)."""
        if self.conn is None:
            self.open()
        period = 1.0 / PHYSICS_HZ
        last = self.clock()
        next_heartbeat = last
        next_parent_check = last + 1.0
        while not self.stopping:
            now = self.clock()
            # A paused process (SIGSTOP) or a slow machine: never step more than 0.2 s.
            dt = min(0.2, max(0.0, now - last)) * self.options.speedup
            last = now
            if self.gps_fix_at is not None and now >= self.gps_fix_at:
                self.gps_fix_at = None
                self.vehicle.gps_fix = self.options.gps_fix
                self.vehicle.satellites = self.options.satellites
            self.vehicle.step(dt, now)
            self._fence_check(now)
            self._gcs_failsafe(now)
            self._mission_news(now)
            if now >= next_heartbeat:
                self._send(heartbeat(self.vehicle, critical=self.gcs_failsafe))
                next_heartbeat = max(next_heartbeat + 1.0, now)
            self._send_streams(now)
            self._send_texts()
            if now >= next_parent_check:
                next_parent_check = now + 1.0
                if self.options.parent_pid and os.getppid() != self.options.parent_pid:
                    log.warning("mavlink sim: parent process gone, stopping")
                    break
            self._poll(max(0.0, now + period - self.clock()))

    # --- receiving --------------------------------------------------------------------
    def _poll(self, timeout: float) -> None:
        """Handle whatever arrives within ``timeout`` seconds (at least one read)."""
        deadline = self.clock() + timeout
        while True:
            try:
                msg = self.conn.recv_match(blocking=False)
            except Exception as exc:  # a broken frame or a dropped TCP peer
                self.bad_frames += 1
                log.debug("mavlink sim: receive error: %s", exc)
                msg = None
            if msg is not None:
                self.handle(msg)
                continue
            remaining = deadline - self.clock()
            if remaining <= 0:
                return
            with contextlib.suppress(Exception):
                self.conn.select(min(remaining, 0.02))

    def handle(self, msg: Any) -> None:
        """Dispatch one received message; never raises for anything a peer sent."""
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.bad_frames += 1
            return
        if kind.startswith("UNKNOWN"):
            self.unknown_messages += 1
            return
        handler = self._handlers.get(kind)
        if kind != "HEARTBEAT":
            log.debug("mavlink sim: %s%s", msg, "" if handler else " (ignored)")
        if handler is None:
            return
        try:
            handler(self, msg)
        except Exception:
            log.exception("mavlink sim: error handling %s", kind)

    def _for_me(self, msg: Any) -> bool:
        target = getattr(msg, "target_system", 0)
        component = getattr(msg, "target_component", 0)
        return target in (0, self.options.sysid) and component in (
            0,
            MAV.MAV_COMP_ID_AUTOPILOT1,
        )

    def _on_heartbeat(self, msg: Any) -> None:
        now = self.clock()
        self.peers[(msg.get_srcSystem(), msg.get_srcComponent())] = now
        if msg.type == MAV.MAV_TYPE_GCS and self.is_gcs(msg.get_srcSystem()):
            self.gcs_last = now
            if self.gcs_failsafe:
                self.gcs_failsafe = False
                self.vehicle.say(MAV.MAV_SEVERITY_WARNING, "GCS Failsafe Cleared")

    def is_gcs(self, sysid: int) -> bool:
        """Whether heartbeats from ``sysid`` count for the GCS fail-safe: SYSID_MYGCS, or
        from 4.7 MAV_GCS_SYSID, or MAV_GCS_SYSID..MAV_GCS_SYSID_HI when HI is not below it."""
        params = self.vehicle.params
        if "MAV_GCS_SYSID" not in params:
            return sysid == int(params["SYSID_MYGCS"])
        low, high = int(params["MAV_GCS_SYSID"]), int(params["MAV_GCS_SYSID_HI"])
        return sysid == low or low <= sysid <= high

    def _on_command_long(self, msg: Any) -> None:
        if not self._for_me(msg):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6)
        self._command(msg, msg.command, params, msg.param7, frame=None)

    def _on_command_int(self, msg: Any) -> None:
        if not self._for_me(msg):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x / 1e7, msg.y / 1e7)
        self._command(msg, msg.command, params, msg.z, frame=msg.frame)

    def _command(
        self, msg: Any, command: int, p: tuple[float, ...], z: float, *, frame: int | None
    ) -> None:
        result, text = self._execute(command, p, z, frame)
        log.debug("mavlink sim: %s -> result %d %s", command, result, text or "")
        if text:
            self.vehicle.say(
                MAV.MAV_SEVERITY_CRITICAL
                if result != MAV.MAV_RESULT_ACCEPTED
                else MAV.MAV_SEVERITY_INFO,
                text,
            )
            # ArduPilot sends the explanation before the ACK; so do we.
            self._send_texts()
        self._send(
            MAV.MAVLink_command_ack_message(
                command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
            )
        )

    def _execute(
        self, command: int, p: tuple[float, ...], z: float, frame: int | None
    ) -> CommandResult:
        """The commands every firmware answers alike; the rest is the vehicle's."""
        v = self.vehicle
        ok, failed = MAV.MAV_RESULT_ACCEPTED, MAV.MAV_RESULT_FAILED
        if command == MAV.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] == 1:
                return v.arm()
            if p[0] == 0:
                return v.disarm(force=int(p[1]) == FORCE_DISARM)
            return failed, "Arm: bad parameter"
        if command == MAV.MAV_CMD_DO_SET_MODE:
            if not int(p[0]) & MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return MAV.MAV_RESULT_UNSUPPORTED, "Mode change: custom mode flag required"
            error = v.set_mode(int(p[1]))
            return (failed, error) if error else (ok, None)
        if command in (MAV.MAV_CMD_DO_GRIPPER, MAV.MAV_CMD_DO_SET_SERVO):
            v.payload_released = True
            return ok, "Gripper load released"
        if command == MAV.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(int(p[0]), p[1])
        if command == MAV.MAV_CMD_GET_MESSAGE_INTERVAL:
            name = self._message_name(int(p[0]))
            interval = self.intervals.get(name or "", -1.0)
            self._send(
                MAV.MAVLink_message_interval_message(
                    int(p[0]), int(interval * 1e6) if interval > 0 else -1
                )
            )
            return ok, None
        if command == MAV.MAV_CMD_REQUEST_MESSAGE:
            name = self._message_name(int(p[0]))
            if name is None or name not in STREAMABLE:
                return MAV.MAV_RESULT_UNSUPPORTED, None
            return self._send_now(name)
        if command == MAV.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return self._send_now("AUTOPILOT_VERSION")
        if command == MAV.MAV_CMD_GET_HOME_POSITION:
            return self._send_now("HOME_POSITION")
        if command == MAV.MAV_CMD_DO_SET_MISSION_CURRENT:
            if not v.mission_set_current(int(p[0])):
                return failed, f"Mission: no item {int(p[0])}"
            return ok, None
        return v.command(command, p, z, frame)

    def _send_now(self, name: str) -> CommandResult:
        """Send ``name`` once; FAILED when there is nothing to send (no home yet)."""
        msg = self._message(name)
        if msg is None:
            return MAV.MAV_RESULT_FAILED, None
        self._send(msg)
        return MAV.MAV_RESULT_ACCEPTED, None

    def _on_set_mode(self, msg: Any) -> None:
        if msg.target_system not in (0, self.options.sysid):
            return
        error = self.vehicle.set_mode(int(msg.custom_mode))
        if error:
            self.vehicle.say(MAV.MAV_SEVERITY_WARNING, error)
            self._send_texts()
        result = MAV.MAV_RESULT_FAILED if error else MAV.MAV_RESULT_ACCEPTED
        # ArduPilot acknowledges SET_MODE with a COMMAND_ACK for command 11 (SET_MODE).
        self._send(
            MAV.MAVLink_command_ack_message(
                MAV.MAVLINK_MSG_ID_SET_MODE,
                result,
                0,
                0,
                msg.get_srcSystem(),
                msg.get_srcComponent(),
            )
        )

    def _on_set_position_target_local_ned(self, msg: Any) -> None:
        if self._for_me(msg):
            target = PositionTarget(
                msg.coordinate_frame, msg.type_mask, msg.x, msg.y, msg.z,
                msg.vx, msg.vy, msg.vz, msg.yaw, msg.yaw_rate,
            )  # fmt: skip
            self.vehicle.local_target(target, self.clock())

    def _on_set_position_target_global_int(self, msg: Any) -> None:
        if self._for_me(msg):
            target = PositionTarget(
                msg.coordinate_frame, msg.type_mask, msg.lat_int / 1e7, msg.lon_int / 1e7,
                msg.alt, msg.vx, msg.vy, msg.vz, msg.yaw, msg.yaw_rate,
            )  # fmt: skip
            self.vehicle.global_target(target, self.clock())

    def _on_param_request_read(self, msg: Any) -> None:
        if not self._for_me(msg):
            return
        names = list(self.param_table)
        if msg.param_index >= 0:
            if msg.param_index < len(names):
                self._send_param(names[msg.param_index])
            return
        name = param_name(msg.param_id)
        if name in self.param_table:
            self._send_param(name)

    def _on_param_request_list(self, msg: Any) -> None:
        if self._for_me(msg):
            for name in self.param_table:
                self._send_param(name)

    def _on_param_set(self, msg: Any) -> None:
        if not self._for_me(msg):
            return
        name = param_name(msg.param_id)
        if name not in self.param_table or not math.isfinite(msg.param_value):
            return  # ArduPilot ignores unknown parameters
        value = float(msg.param_value)
        self.vehicle.params[name] = float(round(value)) if self.param_table[name][1] else value
        self._send_param(name)

    def _on_request_data_stream(self, msg: Any) -> None:
        if not self._for_me(msg):
            return
        names = DATA_STREAMS.get(int(msg.req_stream_id), ())
        rate = float(msg.req_message_rate)
        for name in names:
            if msg.start_stop and rate > 0:
                self._stream(name, 1.0 / min(rate, MAX_STREAM_HZ))
            else:
                self._stream(name, None)

    def _mission_message(self, msg: Any, fence: Any, mission: Any) -> None:
        """A message of the mission protocol: to the fence's transfer or the mission's
        by its mission_type (rally points are not modelled: ignored)."""
        if not self._for_me(msg):
            return
        kind = getattr(msg, "mission_type", MAV.MAV_MISSION_TYPE_MISSION)
        if kind == MAV.MAV_MISSION_TYPE_FENCE:
            self._send_all(fence(msg))
        elif kind == MAV.MAV_MISSION_TYPE_MISSION:
            self._send_all(mission(msg))
            self._send_texts_of(self.mission_transfer.texts)

    def _on_mission_request_list(self, msg: Any) -> None:
        t = self.mission_transfer
        self._mission_message(msg, self.fence_transfer.request_list, t.request_list)

    def _on_mission_count(self, msg: Any) -> None:
        t = self.mission_transfer
        self._mission_message(msg, self.fence_transfer.count, lambda m: t.count(m, self.clock()))

    def _on_mission_item_int(self, msg: Any) -> None:
        t = self.mission_transfer
        self._mission_message(msg, self.fence_transfer.item, lambda m: t.item(m, self.clock()))

    def _on_mission_request_int(self, msg: Any) -> None:
        self._mission_message(msg, self.fence_transfer.request, self.mission_transfer.request)

    def _on_mission_clear_all(self, msg: Any) -> None:
        self._mission_message(msg, self.fence_transfer.clear, self.mission_transfer.clear)

    def _mission_news(self, now: float) -> None:
        """A stalled upload's request again or its cancellation; MISSION_CURRENT when
        AUTO moved on, MISSION_ITEM_REACHED for each item it reached."""
        self._send_all(self.mission_transfer.update(now))
        self._send_texts_of(self.mission_transfer.texts)
        mission = self.vehicle.mission
        if mission.reached or mission.current_changed:
            self._send_texts()  # "Mission: <n> ..." before the news, as ArduPilot says it
        while mission.reached:
            self._send(MAV.MAVLink_mission_item_reached_message(mission.reached.popleft()))
        if mission.current_changed:
            mission.current_changed = False
            self._send(self._message("MISSION_CURRENT"))

    def _send_texts_of(self, texts: Any) -> None:
        while texts:
            self.vehicle.say(*texts.popleft())
        self._send_texts()

    def _on_timesync(self, msg: Any) -> None:
        if msg.tc1 == 0:
            now_ns = int((self.clock() - self.started) * 1e9)
            self._send(MAV.MAVLink_timesync_message(now_ns, msg.ts1))

    _handlers: dict[str, Callable[[Autopilot, Any], None]] = {
        "HEARTBEAT": _on_heartbeat,
        "COMMAND_LONG": _on_command_long,
        "COMMAND_INT": _on_command_int,
        "SET_MODE": _on_set_mode,
        "SET_POSITION_TARGET_LOCAL_NED": _on_set_position_target_local_ned,
        "SET_POSITION_TARGET_GLOBAL_INT": _on_set_position_target_global_int,
        "PARAM_REQUEST_READ": _on_param_request_read,
        "PARAM_REQUEST_LIST": _on_param_request_list,
        "PARAM_SET": _on_param_set,
        "REQUEST_DATA_STREAM": _on_request_data_stream,
        "MISSION_REQUEST_LIST": _on_mission_request_list,
        "MISSION_COUNT": _on_mission_count,
        "MISSION_ITEM_INT": _on_mission_item_int,
        "MISSION_REQUEST_INT": _on_mission_request_int,
        "MISSION_REQUEST": _on_mission_request_int,
        "MISSION_CLEAR_ALL": _on_mission_clear_all,
        "TIMESYNC": _on_timesync,
    }

    # --- fail-safe --------------------------------------------------------------------
    def _gcs_failsafe(self, now: float) -> None:
        """Armed, having heard the GCS and then nothing for as long as the firmware
        allows: the vehicle acts (once, unless its firmware holds off for now)."""
        v = self.vehicle
        after = v.gcs_failsafe_after_s()
        if after is None or self.gcs_failsafe or self.gcs_last is None or not v.armed:
            return
        if now - self.gcs_last <= after:
            return
        self.gcs_failsafe = v.gcs_failsafe()

    # --- sending ----------------------------------------------------------------------
    def _send(self, msg: Any) -> None:
        if msg is None or self.conn is None:
            return
        try:
            self.conn.mav.send(msg)
        except Exception as exc:  # a TCP peer gone, a serial port pulled
            log.debug("mavlink sim: send failed: %s", exc)

    def _send_all(self, messages: list[Any]) -> None:
        for msg in messages:
            self._send(msg)

    def _fence_check(self, now: float) -> None:
        """ArduCopter checks its fence at 25 Hz; a change goes out as FENCE_STATUS."""
        if now < self.next_fence_check:
            return
        self.next_fence_check = now + 1.0 / FENCE_HZ
        if self.vehicle.fence_check():
            self._send_texts()  # "... fence breached" before the status
            fence = self.vehicle.fence
            self._send(
                MAV.MAVLink_fence_status_message(
                    int(fence.breached != 0),
                    fence.breach_count,
                    fence_breach_type(fence.breached),
                    fence.breach_time_ms,
                )
            )

    def _send_texts(self) -> None:
        while self.vehicle.texts:
            severity, text = self.vehicle.texts.popleft()
            self._send(MAV.MAVLink_statustext_message(severity, text.encode()))

    def _send_param(self, name: str) -> None:
        names = list(self.param_table)
        kind = MAV.MAV_PARAM_TYPE_INT32 if self.param_table[name][1] else MAV.MAV_PARAM_TYPE_REAL32
        self._send(
            MAV.MAVLink_param_value_message(
                name.encode(), self.vehicle.params[name], kind, len(names), names.index(name)
            )
        )

    @staticmethod
    def _message_name(msg_id: int) -> str | None:
        cls = MAV.mavlink_map.get(msg_id)
        return None if cls is None else str(cls.msgname)

    def _set_interval(self, msg_id: int, interval_us: float) -> CommandResult:
        name = self._message_name(msg_id)
        if name == "HEARTBEAT":
            return MAV.MAV_RESULT_ACCEPTED, None  # always 1 Hz
        if name is None or name not in STREAMABLE:
            return MAV.MAV_RESULT_UNSUPPORTED, None
        if interval_us < 0:
            self._stream(name, None)
        elif interval_us == 0:
            # "Default rate": back to its stream group's rate, or off where that is 0.
            self._stream(name, self.default_intervals.get(name))
        else:
            self._stream(name, max(1.0 / MAX_STREAM_HZ, interval_us / 1e6))
        return MAV.MAV_RESULT_ACCEPTED, None

    def _stream(self, name: str, interval_s: float | None) -> None:
        if interval_s is None:
            self.intervals.pop(name, None)
            self.next_due.pop(name, None)
        else:
            self.intervals[name] = interval_s
            self.next_due[name] = self.clock()

    def _send_streams(self, now: float) -> None:
        for name, interval in list(self.intervals.items()):
            due = self.next_due.get(name, now)
            if now >= due:
                self._send(self._message(name))
                self.next_due[name] = max(due + interval, now)

    def _message(self, name: str) -> Any:
        """The message ``name`` as of now; None when ArduPilot would send nothing."""
        clocks = Clocks(
            boot_ms=int(self.vehicle.sim_time * 1000) & 0xFFFFFFFF,
            uptime_us=int((self.clock() - self.started) * 1e6),
        )
        return message(
            name, self.vehicle, clocks, sysid=self.options.sysid, firmware=self.options.firmware
        )
