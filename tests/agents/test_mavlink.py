"""The MAVLink quadcopter over real UDP: the agent's adapter flies the simulated
ArduCopter (``python -m agents sim mavlink``, a separate process) through a ControlHub
and its WebSocket server, as a browser would.

Every rig runs the simulator with ``speedup`` so flights take seconds; assertions are
about where the drone goes and what the user is told, with loose time bounds only.
"""

from __future__ import annotations

import asyncio
import math
import os
import signal
import socket
import struct
import threading
import time
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection

from agents.geo import distance_m, local_offset_m
from agents.protocol import Limits
from agents.safety import CommandGate, Refusal
from agents.vehicles.base import AdapterError
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from agents.vehicles.mavlink.config import MavlinkConfig
from agents.vehicles.mavlink.dialect import MAV, mavutil
from agents.vehicles.mavlink.sim import simulator_command
from agents.vehicles.registry import adapter_create
from tests.agents.mavlink_rig import (
    DRONE_COMMANDS,
    HOME,
    LINK_LOSS_TIMEOUT_MS,
    SIM,
    Rig,
    RigFactory,
    ground_station,
    join,
    modes_until,
    poll,
    simulator_listening,
    watch,
)
from tests.control import command


@pytest.fixture
async def rig(make_quad_rig: RigFactory) -> Rig:
    """In this module, one quadcopter rig with the default task (conftest's ``rig`` is
    the control tests' car)."""
    return await make_quad_rig()


async def hold(ws: ClientConnection, name: str, seconds: float, seq0: int, **args: Any) -> int:
    """Hold a key: repeat ``name`` every 100 ms for ``seconds``, as the browser does;
    every repeat must be acknowledged ok. Returns the next free seq."""
    seq = seq0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        ack = await command(ws, seq, name, **args)
        assert ack["ok"], ack
        seq += 1
        await asyncio.sleep(0.1)
    return seq


def metres_from(origin: tuple[float, float], location: dict[str, float]) -> tuple[float, float]:
    return local_offset_m(origin, (location["lat"], location["lon"]))


# --- flying ---------------------------------------------------------------------------


async def test_take_off_rotate_fly_east_ceiling_and_return_home(rig: Rig):
    ws = await join(rig)
    # Position, GPS status and battery come in separate MAVLink messages, in any order.
    data = await watch(
        ws,
        lambda d: (
            d["location"] is not None
            and d["number_of_gps_satellites"] is not None
            and d["battery_level"] is not None
        ),
        5,
        "a position fix, the GPS status and the battery",
    )
    assert data["autopilot_link"] == "ok" and data["is_armed"] is False
    assert data["number_of_gps_satellites"] >= 6 and data["battery_level"] > 90
    home = (data["location"]["lat"], data["location"]["lon"])
    assert distance_m(home, HOME) < 1

    started = time.monotonic()
    ack = await command(ws, 1, "take_off", altitude_m=5)
    assert ack == {"type": "ack", "seq": 1, "ok": True, "error": None}
    rtt_ms = (time.monotonic() - started) * 1000  # GUIDED, arm, NAV_TAKEOFF: three ACKs
    data = await watch(ws, lambda d: d["altitude"] > 4.8, 10, "5 m")
    assert data["is_armed"] is True and data["flight_mode"] == "GUIDED"
    assert data["altitude"] < 5.3
    print(f"take_off (3 COMMAND_ACKs over UDP) acknowledged in {rtt_ms:.1f} ms")

    assert (await command(ws, 2, "rotate_right", angle_deg=90))["ok"]
    data = await watch(ws, lambda d: abs(d["heading"] - 90) < 2, 10, "heading 90")
    before = metres_from(home, data["location"])

    seq = await hold(ws, "front", 2.0, 3, speed_mps=2)
    data = await watch(ws, lambda d: d["speed"] < 0.2, 10, "the drone to stop")
    north, east = metres_from(home, data["location"])
    assert east - before[1] > 4, (north, east)  # 2 s at 2 m/s (x4 flight time), braking
    assert abs(north - before[0]) < 1.0, (north, east)  # east, not north: body frame
    assert abs(data["heading"] - 90) < 2  # velocity setpoints hold the heading

    refused = await command(ws, seq, "up", speed_mps=2)
    assert refused["ok"] is False and refused["code"] == "altitude_limit"
    assert "6 m limit" in refused["error"]

    assert (await command(ws, seq + 1, "return_to_home"))["ok"]
    data = await watch(ws, lambda d: d["flight_mode"] == "RTL", 3, "RTL")
    data = await watch(ws, lambda d: d["is_armed"] is False, 30, "landed and disarmed")
    assert data["altitude"] < 0.2
    assert distance_m(home, (data["location"]["lat"], data["location"]["lon"])) < 2
    assert rig.drone.stats["refusals"] == 0
    await ws.close()


async def test_killed_controller_triggers_return_home_and_landing(rig: Rig):
    ws = await join(rig)
    assert (await command(ws, 1, "take_off", altitude_m=4))["ok"]
    await watch(ws, lambda d: (d["altitude"] or 0) > 3.8, 10, "4 m")
    await hold(ws, "right", 1.0, 2, speed_mps=3)
    data = await watch(ws, lambda d: True, 1, "telemetry")
    assert distance_m(HOME, (data["location"]["lat"], data["location"]["lon"])) > 2

    killed = time.monotonic()
    ws.transport.abort()
    # The agent holds the drone for the link-loss timeout (the same user may come back,
    # a reload), then acts: wait past that timeout, with room for a loaded machine.
    await poll(
        lambda: bool(rig.reported("failsafe")), LINK_LOSS_TIMEOUT_MS / 1000 + 8, "the fail-safe"
    )
    assert rig.reported("failsafe") == [{"cause": "link_lost", "action": "return_to_home"}]
    assert rig.drone.t.mode == 6  # RTL, acknowledged by the autopilot
    await poll(lambda: rig.drone.t.armed is False, 30, "landing and disarming")
    assert time.monotonic() - killed < 30
    t = rig.drone.t
    assert t.alt is not None and t.alt < 0.2
    assert t.lat is not None and t.lon is not None and distance_m(HOME, (t.lat, t.lon)) < 2


async def test_autopilot_refusal_reaches_the_user_in_its_words(make_quad_rig: RigFactory):
    rig = await make_quad_rig(simulator={**SIM, "gps": "none"})
    ws = await join(rig)
    ack = await command(ws, 1, "arm")
    assert ack["ok"] is False and ack["code"] == "autopilot_refused"
    # Named: the user's command, then the autopilot's words.
    assert ack["error"].startswith("arm: autopilot refused MAV_CMD_COMPONENT_ARM_DISARM: ")
    assert "temporarily rejected" in ack["error"] and "PreArm: GPS: no 3D fix" in ack["error"]
    ack = await command(ws, 2, "take_off", altitude_m=3)
    assert ack["code"] == "autopilot_refused" and "GPS" in ack["error"]
    # Moving needs a flying drone: refused by the agent, nothing sent.
    ack = await command(ws, 3, "front")
    assert ack["code"] == "not_flying" and "take off first" in ack["error"]
    assert rig.reported("command_refused")[0]["code"] == "autopilot_refused"
    assert ("autopilot_warning", {"severity": 2, "text": "PreArm: GPS: no 3D fix"}) in rig.events
    await ws.close()


class ScriptedAutopilot:
    """A stand-in autopilot on a UDP port (pymavlink, a thread): heartbeats at 5 Hz, and
    each arming command answered as the test scripted it: ``(texts, result)``, the texts
    ``(severity, words)`` sent just before the COMMAND_ACK, as ArduPilot does."""

    def __init__(self) -> None:
        self.conn = mavutil.mavlink_connection(
            "udpin:127.0.0.1:0", source_system=1, source_component=1
        )
        self.port = int(self.conn.port.getsockname()[1])
        self.script: list[tuple[list[tuple[int, str]], int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def say(self, severity: int, text: str) -> None:
        self.conn.mav.statustext_send(severity, text.encode())

    def _run(self) -> None:
        next_beat = 0.0
        while not self._stop.is_set():
            if time.monotonic() >= next_beat:
                self.conn.mav.heartbeat_send(
                    MAV.MAV_TYPE_QUADROTOR, MAV.MAV_AUTOPILOT_ARDUPILOTMEGA,
                    MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, MAV.MAV_STATE_STANDBY,
                )  # fmt: skip
                next_beat = time.monotonic() + 0.2
            msg = self.conn.recv_match(type="COMMAND_LONG", blocking=True, timeout=0.05)
            if msg is None:
                continue
            result = MAV.MAV_RESULT_ACCEPTED
            if msg.command == MAV.MAV_CMD_COMPONENT_ARM_DISARM and self.script:
                texts, result = self.script.pop(0)
                for severity, text in texts:
                    self.say(severity, text)
            self.conn.mav.command_ack_send(msg.command, result)

    def __enter__(self) -> ScriptedAutopilot:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2)
        self.conn.close()


async def test_a_refusal_quotes_only_the_autopilots_answer_to_that_command():
    """ArduPilot explains a refusal in a STATUSTEXT (WARNING or worse) just before its
    COMMAND_ACK. What else it says meanwhile ("Throttle armed"), or said before the
    command, is no reason for this refusal."""
    with ScriptedAutopilot() as autopilot:
        drone = adapter_create(
            "mavlink",
            {"connection": f"udpout:127.0.0.1:{autopilot.port}", "command_timeout_s": 2.0},
        )
        assert isinstance(drone, MavlinkAdapter)
        async with drone:
            info, critical = MAV.MAV_SEVERITY_INFO, MAV.MAV_SEVERITY_CRITICAL
            autopilot.script = [
                ([(info, "Throttle armed")], MAV.MAV_RESULT_FAILED),
                ([(critical, "Arm: Radio failsafe on")], MAV.MAV_RESULT_TEMPORARILY_REJECTED),
                ([], MAV.MAV_RESULT_DENIED),
            ]
            with pytest.raises(AdapterError) as refused:
                await drone.execute("arm", {})
            assert "Throttle armed" not in str(refused.value)
            assert str(refused.value).endswith("failed (the autopilot tried and could not)")
            with pytest.raises(AdapterError) as refused:
                await drone.execute("arm", {})
            assert str(refused.value).endswith("temporarily rejected (Arm: Radio failsafe on)")
            # A warning of earlier, then a refusal with no words of its own.
            autopilot.say(MAV.MAV_SEVERITY_WARNING, "PreArm: Compass not calibrated")
            await poll(lambda: any("Compass" in t for _, _, t in drone.texts), 5, "the text")
            with pytest.raises(AdapterError) as refused:
                await drone.execute("arm", {})
            assert "Compass" not in str(refused.value)
            assert str(refused.value).endswith(
                "denied (the autopilot does not allow it in its current state)"
            )


async def test_unanswered_command_is_a_timeout(make_quad_rig: RigFactory):
    rig = await make_quad_rig(heartbeat_timeout_s=5.0, command_timeout_s=1.0)
    process = rig.sim_process
    assert process is not None
    os.kill(process.pid, signal.SIGSTOP)  # silent for less than the heartbeat timeout
    try:
        started = time.monotonic()
        with pytest.raises(AdapterError) as refused:
            await rig.drone.execute("arm", {})
        assert refused.value.code == "timeout"
        assert "did not answer MAV_CMD_DO_SET_MODE (GUIDED) within 1 s" in str(refused.value)
        assert 0.9 < time.monotonic() - started < 3
    finally:
        os.kill(process.pid, signal.SIGCONT)


async def test_a_closed_link_refuses_commands_at_once(rig: Rig):
    """Once the agent has closed its link (shutting down, or killed mid-mission), what
    is still asked of the drone, a shutdown's safe action above all, is refused for the
    closed link instead of waiting for answers nothing could carry."""
    await rig.drone.execute("arm", {})
    await rig.drone.close()
    with pytest.raises(AdapterError) as refused:
        await rig.drone.execute("disarm", {})
    assert refused.value.code == "not_ready" and "link is not open" in str(refused.value)
    with pytest.raises(AdapterError) as refused:  # as a mission's runner sends them
        await rig.drone.link.command_long(MAV.MAV_CMD_COMPONENT_ARM_DISARM, (0,))
    assert refused.value.code == "autopilot_lost"
    assert "the link to the autopilot is closed" in str(refused.value)
    await rig.drone.safe_action("return_to_home")
    failed = (
        "safe_action_failed",
        {"action": "return_to_home", "reason": "no link to the autopilot"},
    )
    assert failed in rig.events
    assert rig.drone.link.stats["timeouts"] == 0  # nothing was sent to wait for


# --- bad input and silence --------------------------------------------------------------


def _frame_v2(msg_id: int, payload: bytes, *, seq: int = 0, crc: int = 0) -> bytes:
    header = struct.pack(
        "<BBBBBBBHB", 0xFD, len(payload), 0, 0, seq, 1, 1, msg_id & 0xFFFF, msg_id >> 16
    )
    return header + payload + struct.pack("<H", crc)


async def test_bad_bytes_from_the_autopilot_side_never_crash_the_agent(rig: Rig):
    drone = rig.drone
    port = drone.local_port()
    assert port is not None
    good = MAV.MAVLink_heartbeat_message(2, 3, 0, 0, 3, 3).pack(MAV.MAVLink(None, 1, 1))
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    garbage = [
        os.urandom(300),
        bytes(bad_crc),
        _frame_v2(60_123, b"\x01\x02\x03", crc=0xBEEF),  # an id no dialect has
        good[:7],  # truncated
        b"\xfd" * 64,
        b"",
    ]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _ in range(20):
            for chunk in garbage:
                s.sendto(chunk, ("127.0.0.1", port))
        await asyncio.sleep(0.5)
    assert drone.bad_frames > 20
    assert all(thread.is_alive() for thread in drone.link.threads)
    assert drone.link_ok
    # Still flying normally: commands are acknowledged, telemetry is fresh.
    await drone.execute("arm", {})
    assert drone.t.armed is True
    await drone.execute("disarm", {})
    # The position stream is fresh (on a loaded machine its first message may lag).
    for _ in range(50):
        if time.monotonic() - drone.t.position_at < 1:
            break
        await asyncio.sleep(0.1)
    assert time.monotonic() - drone.t.position_at < 1


async def test_autopilot_silence_is_reported_and_refuses_commands(rig: Rig):
    ws = await join(rig)
    await watch(ws, lambda d: d["location"] is not None, 5, "a position")
    process = rig.sim_process
    assert process is not None
    os.kill(process.pid, signal.SIGSTOP)  # the autopilot goes silent
    try:
        data = await watch(ws, lambda d: d["autopilot_link"] == "lost", 5, "link lost")
        assert "autopilot_link_lost" in rig.event_names()
        ack = await command(ws, 1, "take_off", altitude_m=3)
        assert ack["ok"] is False and ack["code"] == "autopilot_lost"
        assert "no heartbeat from the autopilot" in ack["error"]
        assert data["location"] is not None  # last known values stay visible
    finally:
        os.kill(process.pid, signal.SIGCONT)
    await watch(ws, lambda d: d["autopilot_link"] == "ok", 5, "link back")
    assert "autopilot_link_restored" in rig.event_names()
    assert (await command(ws, 2, "arm"))["ok"]
    await ws.close()


# --- safety -----------------------------------------------------------------------------


async def test_low_battery_returns_home_once_and_reports_it(make_quad_rig: RigFactory):
    # 27 % and 240 %/min of flight time at 4x: below 25 % about 0.1 s into the flight.
    rig = await make_quad_rig(
        simulator={**SIM, "battery_pct": 27, "drain_pct_per_min": 240}, low_battery_pct=25
    )
    ws = await join(rig)
    assert (await command(ws, 1, "take_off", altitude_m=4))["ok"]
    await watch(ws, lambda d: d["flight_mode"] == "RTL", 10, "the low-battery RTL")
    [data] = [d for n, d in rig.events if n == "low_battery"]
    assert data["action"] == "return_to_home" and data["battery"] < 25
    ack = await command(ws, 2, "front")
    assert ack["code"] == "low_battery" and "returning home" in ack["error"]
    ack = await command(ws, 3, "take_off", altitude_m=4)
    assert ack["code"] == "in_air"
    await watch(ws, lambda d: d["is_armed"] is False, 30, "landed")
    assert rig.event_names().count("low_battery") == 1
    await ws.close()


async def test_failsafe_parameters_are_checked_against_the_task(make_quad_rig: RigFactory):
    rig = await make_quad_rig()  # the spawned simulator has FS_GCS_ENABLE=1 (RTL)
    drone = rig.drone
    assert await drone.check_failsafe_params("return_to_home") == []
    [problem] = await drone.check_failsafe_params("land")
    assert "does RTL (else LAND) (FS_GCS_ENABLE=1) but the task expects land" in problem
    [problem] = await drone.check_failsafe_params("return_to_home", max_altitude_m=4)
    assert "RTL climbs to 6 m (RTL_ALT=600 cm), above the task's 4 m ceiling" in problem

    stock = await make_quad_rig(
        simulator={"params": {"FS_GCS_ENABLE": 0, "SYSID_MYGCS": 250}}, command_timeout_s=1.0
    )
    problems = await stock.drone.check_failsafe_params("return_to_home")
    assert len(problems) == 2
    assert "GCS fail-safe is disabled (FS_GCS_ENABLE=0)" in problems[0]
    assert "follows system 250 (SYSID_MYGCS) but the agent is system 255" in problems[1]


async def test_failsafe_check_reads_the_gcs_id_under_either_name(make_quad_rig: RigFactory):
    """ArduPilot 4.7 renamed SYSID_MYGCS to MAV_GCS_SYSID (with MAV_GCS_SYSID_HI for a
    range): the check reads the newer name first and says which one the autopilot has."""
    legacy = await make_quad_rig()  # ArduCopter 4.5: SYSID_MYGCS
    assert await legacy.drone.check_failsafe_params("return_to_home") == []
    assert legacy.drone.gcs_sysid_param == "SYSID_MYGCS"

    current = await make_quad_rig(simulator={**SIM, "firmware": "4.7"})
    assert await current.drone.check_failsafe_params("return_to_home") == []
    assert current.drone.gcs_sysid_param == "MAV_GCS_SYSID"

    params = {"FS_GCS_ENABLE": 1, "MAV_GCS_SYSID": 250}
    other = await make_quad_rig(simulator={**SIM, "firmware": "4.7", "params": params})
    [problem] = await other.drone.check_failsafe_params("return_to_home")
    assert problem == (
        "the autopilot's GCS fail-safe follows system 250 (MAV_GCS_SYSID) but the agent is "
        "system 255: it would never see the agent's heartbeats"
    )
    ranged = {"FS_GCS_ENABLE": 1, "MAV_GCS_SYSID": 250, "MAV_GCS_SYSID_HI": 255}
    within = await make_quad_rig(simulator={**SIM, "firmware": "4.7", "params": ranged})
    assert await within.drone.check_failsafe_params("return_to_home") == []
    apart = {"FS_GCS_ENABLE": 1, "MAV_GCS_SYSID": 200, "MAV_GCS_SYSID_HI": 210}
    outside = await make_quad_rig(simulator={**SIM, "firmware": "4.7", "params": apart})
    [problem] = await outside.drone.check_failsafe_params("return_to_home")
    assert "follows systems 200-210 (MAV_GCS_SYSID, MAV_GCS_SYSID_HI) but the agent is" in problem


async def test_failsafe_check_names_both_gcs_id_parameters_when_unanswered(
    make_quad_rig: RigFactory,
):
    rig = await make_quad_rig(heartbeat_timeout_s=5.0, command_timeout_s=1.0)
    process = rig.sim_process
    assert process is not None
    os.kill(process.pid, signal.SIGSTOP)  # silent for less than the heartbeat timeout
    try:
        problems = await rig.drone.check_failsafe_params("return_to_home")
    finally:
        os.kill(process.pid, signal.SIGCONT)
    assert problems == [
        "the autopilot did not answer for parameter FS_GCS_ENABLE within 1 s",
        "the autopilot did not answer for parameter FS_GCS_TIMEOUT within 1 s",
        "the autopilot did not answer for parameter MAV_GCS_SYSID or SYSID_MYGCS within 1 s",
    ]
    assert rig.drone.gcs_sysid_param is None


async def test_no_position_before_the_autopilots_gps_fix(make_quad_rig: RigFactory):
    """Before its first fix ArduCopter reports 0/0 with no satellites: users and the
    platform (the agent's heartbeat carries ``state()``'s position) get none at all."""
    rig = await make_quad_rig(simulator={**SIM, "gps_fix_after_s": 6})
    drone = rig.drone
    ws = await join(rig)

    def searching(d: dict[str, Any]) -> bool:
        return d["number_of_gps_satellites"] == 0 and d["altitude"] is not None

    data = await watch(ws, searching, 6, "telemetry from an autopilot without a fix")
    assert data["location"] is None and data["autopilot_link"] == "ok"
    assert drone.telemetry()["gps_fix"] == "none"
    assert drone.t.position_at > 0  # GLOBAL_POSITION_INT did come: 0/0
    assert (drone.state().lat, drone.state().lon) == (None, None)

    data = await watch(ws, lambda d: d["location"] is not None, 15, "a position after the fix")
    assert distance_m(HOME, (data["location"]["lat"], data["location"]["lon"])) < 1
    assert data["number_of_gps_satellites"] >= 6 and drone.telemetry()["gps_fix"] == "3D"
    assert drone.state().lat is not None
    assert (await command(ws, 1, "take_off", altitude_m=3))["ok"]
    await ws.close()


async def test_movement_is_refused_before_take_off_and_the_gate_checks_projections(rig: Rig):
    drone = rig.drone
    with pytest.raises(AdapterError) as refused:
        await drone.execute("up", {"speed_mps": 1})
    assert refused.value.code == "not_flying"
    gate = CommandGate(drone, allowed=DRONE_COMMANDS, limits=Limits(max_altitude_m=6))
    with pytest.raises(Refusal) as too_high:
        gate.check("take_off", {"altitude_m": 7})
    assert too_high.value.code == "altitude_limit"
    assert gate.check("take_off", {"altitude_m": 6}).args == {"altitude_m": 6}
    far = Limits(geofence_center=HOME, geofence_radius_m=50)
    with pytest.raises(Refusal) as fenced:
        CommandGate(drone, allowed=DRONE_COMMANDS, limits=far).check(
            "go_to_waypoint", {"lat": HOME[0] + 0.001, "lon": HOME[1], "alt_m": 5}
        )
    assert fenced.value.code == "geofence"


def test_projection_turns_the_body_axes_by_the_heading():
    drone = adapter_create("mavlink", {"connection": "udpin:127.0.0.1:0", "setpoint_hold_s": 1.0})
    assert isinstance(drone, MavlinkAdapter)
    t = drone.t
    t.lat, t.lon, t.alt, t.heading = HOME[0], HOME[1], 5.0, 90.0
    front = drone.project("front", {"speed_mps": 2})
    assert front is not None and front.lat is not None and front.lon is not None
    north, east = local_offset_m(HOME, (front.lat, front.lon))
    assert math.isclose(east, 2, abs_tol=0.01) and abs(north) < 0.01
    left = drone.project("left", {"speed_mps": 1})
    assert left is not None and left.lat is not None and left.lon is not None
    north, east = local_offset_m(HOME, (left.lat, left.lon))
    assert math.isclose(north, 1, abs_tol=0.01) and abs(east) < 0.01
    up = drone.project("up", {"speed_mps": 1.5})
    assert up is not None and up.alt == 6.5
    assert drone.project("rotate_left", {"angle_deg": 10}) is None


def test_options_are_checked():
    assert MavlinkConfig.from_options({}).source_system == 255
    for bad, named in (
        ({"simulate": "yes"}, "simulate"),
        ({"velocity_frame": "local_ned"}, "velocity_frame"),
        ({"command_timeout_s": 0}, "command_timeout_s"),
        ({"origin": [91, 0]}, "origin"),
        ({"stream_rates_hz": {"NOT_A_MESSAGE": 1}}, "stream_rates_hz"),
        ({"payload": {"method": "servo", "servo": 40, "pwm": 1900}}, "payload.servo"),
        ({"heartbeat_timeout": 2}, "unknown key heartbeat_timeout"),
    ):
        with pytest.raises(ValueError, match=named):
            MavlinkConfig.from_options(bad)
    for bad_simulator, named in (
        ({"gps": "maybe"}, "simulator.gps"),
        ({"firmware": "5.0"}, "simulator.firmware"),
        ({"gps_fix_after_s": "soon"}, "simulator.gps_fix_after_s"),
        ({"speed_up": 4}, "unknown key speed_up"),
    ):
        with pytest.raises(ValueError, match=named):
            simulator_command(bad_simulator, home=HOME)
    names = [c.name for c in adapter_create("mavlink", {}).commands()]
    assert set(DRONE_COMMANDS) <= set(names)
    keys = {c.name: c.key for c in adapter_create("mavlink", {}).commands()}
    assert keys["up"] == "w" and keys["rotate_right"] == "d" and keys["front"] == "ArrowUp"
    assert keys["land"] == "l" and keys["return_to_home"] == "h"


async def test_a_dead_agent_leaves_the_drone_to_the_autopilots_own_failsafe():
    """A real deployment's path: the adapter reaches an autopilot it did not start
    (``connection``). When the agent dies its heartbeats stop, and the autopilot's GCS
    fail-safe (FS_GCS_ENABLE=1, after FS_GCS_TIMEOUT) brings the drone home."""
    with simulator_listening(
        "--home", f"{HOME[0]},{HOME[1]}",
        "--speedup", "4", "--param", "FS_GCS_ENABLE=1", "--param", "FS_GCS_TIMEOUT=1",
    ) as (_, address):  # fmt: skip
        drone = adapter_create("mavlink", {"connection": address, "close_action": "none"})
        assert isinstance(drone, MavlinkAdapter)
        async with drone:
            assert await drone.check_failsafe_params("return_to_home") == []
            await drone.execute("take_off", {"altitude_m": 3})
            await poll(lambda: (drone.t.alt or 0) > 2.5, 5, "3 m")
            assert drone.t.mode == 4
        # The agent is gone (close_action "none": like a crash). Listen as another GCS.
        with ground_station(address) as observer:
            modes = await modes_until(observer, until=6, within=10)
        assert 6 in modes, f"no RTL after the agent died; modes seen {modes}"


async def test_held_rotate_key_stops_turning_on_release(rig: Rig):
    ws = await join(rig)
    assert (await command(ws, 1, "take_off", altitude_m=3))["ok"]
    data = await watch(ws, lambda d: (d["altitude"] or 0) > 2.8, 10, "3 m")
    start = data["heading"]
    seq = await hold(ws, "rotate_right", 1.0, 2, angle_deg=15)
    # The browser sends "stop" when the key is released: the turn ends there.
    assert (await command(ws, seq, "stop"))["ok"]
    released = (await watch(ws, lambda d: True, 1, "telemetry"))["heading"]
    assert (released - start) % 360 > 30  # it did turn while the key was held
    await asyncio.sleep(1.0)
    after = (await watch(ws, lambda d: True, 1, "telemetry"))["heading"]
    assert abs(((after - released) + 180) % 360 - 180) < 20, (start, released, after)
    await ws.close()


async def test_payload_release_is_acknowledged(make_quad_rig: RigFactory):
    rig = await make_quad_rig(payload={"method": "gripper"})
    names = [c.name for c in rig.drone.commands()]
    assert "release_payload" in names
    await rig.drone.execute("release_payload", {})
    assert rig.drone.stats["acks"] > 0 and rig.drone.stats["refusals"] == 0
    with pytest.raises(ValueError):
        MavlinkConfig.from_options({"payload": {"method": "servo", "servo": 99, "pwm": 1900}})
