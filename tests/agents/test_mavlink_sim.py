"""The MAVLink simulator as a plain ground station sees it (pymavlink over real UDP):
what it streams unasked, how stream requests change that, its GPS before and after the
fix, and the parameter names of the ArduCopter release it plays.

Time is read from the simulator itself: its heartbeats (1 Hz) and the boot time in its
messages, so a loaded machine slows the simulator and the test alike.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from agents.geo import distance_m, offset
from agents.vehicles.mavlink.dialect import MAV, mavutil
from agents.vehicles.mavlink.sim import BOAT_SIM_ORIGIN as BOAT_HOME
from agents.vehicles.mavlink.sim.autopilot import Autopilot, SimOptions
from tests.agents.mavlink_rig import HOME, ROOT, simulator_listening

GCS_SYSID = 255


@contextmanager
def simulator(*args: str) -> Iterator[Any]:
    """The simulator in its own process, and a pymavlink ground station (system 255)
    talking to it; both closed at the end. Only a heartbeat is sent, so the simulator
    knows where to send: no stream is asked for."""
    home = () if "--home" in args else ("--home", f"{HOME[0]},{HOME[1]}")
    with simulator_listening(*home, *args) as (_, address):
        gcs = mavutil.mavlink_connection(address, source_system=GCS_SYSID, source_component=190)
        try:
            gcs.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            yield gcs
        finally:
            gcs.close()


def first(
    gcs: Any, kind: str | list[str], within: float, where: Callable[[Any], bool] = lambda m: True
) -> Any:
    """The first ``kind`` message for which ``where`` holds, within ``within`` s."""
    deadline = time.monotonic() + within
    while (left := deadline - time.monotonic()) > 0:
        msg = gcs.recv_match(type=kind, blocking=True, timeout=min(0.5, left))
        if msg is not None and where(msg):
            return msg
    raise AssertionError(f"no {kind} within {within:g} s")


def count_until_heartbeats(
    gcs: Any, kind: str, heartbeats: int, where: Callable[[Any], bool] = lambda m: True
) -> int:
    """How many ``kind`` messages (for which ``where`` holds) arrive before the
    simulator's next ``heartbeats`` heartbeats (one a second of its clock)."""
    seen = beats = 0
    deadline = time.monotonic() + 10 * heartbeats
    while beats < heartbeats:
        assert time.monotonic() < deadline, "the simulator stopped sending heartbeats"
        msg = gcs.recv_match(type=[kind, "HEARTBEAT"], blocking=True, timeout=0.5)
        if msg is None:
            continue
        if msg.get_type() == "HEARTBEAT":
            beats += 1
        elif where(msg):
            seen += 1
    return seen


def message_interval(gcs: Any, name: str) -> int:
    """The simulator's interval for message ``name`` (MAV_CMD_GET_MESSAGE_INTERVAL),
    in µs; -1: not streamed. Everything it sent before the answer has been received."""
    msg_id = getattr(MAV, f"MAVLINK_MSG_ID_{name}")
    gcs.mav.command_long_send(1, 1, MAV.MAV_CMD_GET_MESSAGE_INTERVAL, 0, msg_id, 0, 0, 0, 0, 0, 0)
    answer = first(gcs, "MESSAGE_INTERVAL", 5, lambda m: m.message_id == msg_id)
    return int(answer.interval_us)


def command(gcs: Any, command: int, *params: float) -> int:
    """COMMAND_LONG ``command``; returns its COMMAND_ACK result."""
    p = [*params] + [0.0] * (7 - len(params))
    gcs.mav.command_long_send(1, 1, command, 0, *p)
    return int(first(gcs, "COMMAND_ACK", 5, lambda m: m.command == command).result)


def requested(gcs: Any, kind: str, command: int, *params: float) -> Any:
    """``kind``, asked for with COMMAND_LONG ``command`` (it comes before the ACK)."""
    p = [*params] + [0.0] * (7 - len(params))
    gcs.mav.command_long_send(1, 1, command, 0, *p)
    return first(gcs, kind, 5)


def read_param(gcs: Any, name: str, within: float = 2.0) -> float | None:
    """PARAM_REQUEST_READ ``name``: its value, or None if unanswered within ``within``."""
    gcs.mav.param_request_read_send(1, 1, name.encode(), -1)
    try:
        return float(first(gcs, "PARAM_VALUE", within, lambda m: m.param_id == name).param_value)
    except AssertionError:
        return None


# --- streams --------------------------------------------------------------------------


def test_telemetry_streams_to_a_ground_station_that_asked_for_nothing():
    with simulator() as gcs:
        position = first(gcs, "GLOBAL_POSITION_INT", 5)
        assert distance_m(HOME, (position.lat / 1e7, position.lon / 1e7)) < 1
        assert position.relative_alt == 0
        for kind in ("SYS_STATUS", "GPS_RAW_INT", "ATTITUDE", "VFR_HUD", "BATTERY_STATUS"):
            first(gcs, kind, 5)
        # Every stream group at 1 Hz, the default of ArduPilot's stream-rate parameters
        # (ArduPlane, ArduRover).
        for name in ("GLOBAL_POSITION_INT", "ATTITUDE", "VFR_HUD", "EKF_STATUS_REPORT"):
            assert message_interval(gcs, name) == 1_000_000, name


def test_stream_requests_change_what_streams():
    with simulator() as gcs:
        first(gcs, "GLOBAL_POSITION_INT", 5)
        # REQUEST_DATA_STREAM stop: the POSITION group stops, the others go on.
        gcs.mav.request_data_stream_send(1, 1, MAV.MAV_DATA_STREAM_POSITION, 0, 0)
        assert message_interval(gcs, "GLOBAL_POSITION_INT") == -1
        assert message_interval(gcs, "LOCAL_POSITION_NED") == -1
        assert message_interval(gcs, "ATTITUDE") == 1_000_000
        assert count_until_heartbeats(gcs, "GLOBAL_POSITION_INT", 2) == 0
        # ... and starts again at the rate asked for.
        gcs.mav.request_data_stream_send(1, 1, MAV.MAV_DATA_STREAM_POSITION, 5, 1)
        assert message_interval(gcs, "GLOBAL_POSITION_INT") == 200_000

        # SET_MESSAGE_INTERVAL changes one message: 10 Hz.
        position = MAV.MAVLINK_MSG_ID_GLOBAL_POSITION_INT
        interval = MAV.MAV_CMD_SET_MESSAGE_INTERVAL
        assert command(gcs, interval, position, 100_000) == MAV.MAV_RESULT_ACCEPTED
        assert message_interval(gcs, "GLOBAL_POSITION_INT") == 100_000
        assert count_until_heartbeats(gcs, "GLOBAL_POSITION_INT", 2) >= 8  # about 20
        assert message_interval(gcs, "LOCAL_POSITION_NED") == 200_000
        # 0 is "the default rate": the stream group's default, 1 Hz.
        assert command(gcs, interval, position, 0) == MAV.MAV_RESULT_ACCEPTED
        assert message_interval(gcs, "GLOBAL_POSITION_INT") == 1_000_000
        # -1 stops it.
        assert command(gcs, interval, position, -1) == MAV.MAV_RESULT_ACCEPTED
        assert message_interval(gcs, "GLOBAL_POSITION_INT") == -1
        assert count_until_heartbeats(gcs, "GLOBAL_POSITION_INT", 2) == 0


def test_stream_rate_zero_streams_nothing_until_asked_as_arducopter():
    with simulator("--stream-rate", "0") as gcs:
        assert count_until_heartbeats(gcs, "GLOBAL_POSITION_INT", 2) == 0
        assert message_interval(gcs, "GLOBAL_POSITION_INT") == -1
        position, interval = MAV.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 0
        # "Default rate" where the default is 0: still nothing.
        assert command(gcs, MAV.MAV_CMD_SET_MESSAGE_INTERVAL, position, interval) == 0
        assert message_interval(gcs, "GLOBAL_POSITION_INT") == -1
        gcs.mav.request_data_stream_send(1, 1, MAV.MAV_DATA_STREAM_ALL, 2, 1)
        first(gcs, "GLOBAL_POSITION_INT", 5)
        assert message_interval(gcs, "GLOBAL_POSITION_INT") == 500_000


# --- the GPS fix ------------------------------------------------------------------------


def test_before_its_gps_fix_the_simulator_reports_0_0_and_no_home():
    fix_after_s = 4.0
    with simulator("--gps-fix-after", str(fix_after_s)) as gcs:
        # Before the fix, as ArduCopter: no fix, no satellites, position 0/0, no home.
        raw = first(gcs, "GPS_RAW_INT", 5)
        assert raw.time_usec < fix_after_s * 1e6, "the fix came before the first message"
        assert (raw.fix_type, raw.satellites_visible, raw.lat, raw.lon) == (1, 0, 0, 0)
        position = first(gcs, "GLOBAL_POSITION_INT", 5)
        if position.time_boot_ms < fix_after_s * 1000:
            assert (position.lat, position.lon) == (0, 0)
        arm = command(gcs, MAV.MAV_CMD_DO_SET_MODE, 1, 4)  # GUIDED, disarmed: allowed
        assert arm == MAV.MAV_RESULT_ACCEPTED
        if first(gcs, "GPS_RAW_INT", 5).fix_type < 3:
            assert command(gcs, MAV.MAV_CMD_GET_HOME_POSITION) == MAV.MAV_RESULT_FAILED
            refused = command(gcs, MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            assert refused == MAV.MAV_RESULT_TEMPORARILY_REJECTED
        # The fix: satellites, a position at home, a home, and the EKF's word for it.
        fixed = first(gcs, "GPS_RAW_INT", fix_after_s + 10, lambda m: m.fix_type == 3)
        assert fixed.satellites_visible >= 6
        position = first(gcs, "GLOBAL_POSITION_INT", 5, lambda m: m.lat != 0)
        assert distance_m(HOME, (position.lat / 1e7, position.lon / 1e7)) < 1
        home = requested(gcs, "HOME_POSITION", MAV.MAV_CMD_GET_HOME_POSITION)
        assert distance_m(HOME, (home.latitude / 1e7, home.longitude / 1e7)) < 1


# --- parameter names ----------------------------------------------------------------------


def test_the_gcs_id_has_the_name_of_the_firmware_release():
    with simulator() as gcs:  # ArduCopter 4.5
        assert read_param(gcs, "SYSID_MYGCS") == GCS_SYSID
        assert read_param(gcs, "MAV_GCS_SYSID", within=1) is None  # no answer, as ArduPilot
    with simulator("--firmware", "4.7", "--param", "MAV_GCS_SYSID=250") as gcs:
        assert read_param(gcs, "MAV_GCS_SYSID") == 250
        assert read_param(gcs, "MAV_GCS_SYSID_HI") == 0
        assert read_param(gcs, "MAV_SYSID") == 1
        assert read_param(gcs, "SYSID_MYGCS", within=1) is None
        version = requested(
            gcs,
            "AUTOPILOT_VERSION",
            MAV.MAV_CMD_REQUEST_MESSAGE,
            MAV.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
        ).flight_sw_version
        assert (version >> 24, version >> 16 & 0xFF) == (4, 7)


def test_an_unknown_parameter_for_the_release_is_refused_on_the_command_line():
    sim = subprocess.Popen(
        [
            sys.executable, "-m", "agents", "sim", "mavlink",
            "--firmware", "4.7", "--param", "SYSID_MYGCS=250",
        ],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    _, err = sim.communicate(timeout=30)
    assert sim.returncode == 2
    assert "ArduCopter 4.7 has no parameter SYSID_MYGCS" in err


def armed_then_silent(gcs: Any) -> None:
    """Arm on the ground in GUIDED, then send nothing more (the heartbeat on connecting
    was the last)."""
    assert command(gcs, MAV.MAV_CMD_DO_SET_MODE, 1, 4) == MAV.MAV_RESULT_ACCEPTED
    assert command(gcs, MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1) == MAV.MAV_RESULT_ACCEPTED


def test_the_gcs_failsafe_follows_the_range_of_gcs_ids():
    """ArduPilot 4.7: heartbeats from MAV_GCS_SYSID..MAV_GCS_SYSID_HI count; once they
    stop for FS_GCS_TIMEOUT the armed copter's fail-safe acts (on the ground: disarm).
    A GCS outside the range is never heard, so its silence triggers nothing."""
    failsafe = ["--param", "FS_GCS_ENABLE=1", "--param", "FS_GCS_TIMEOUT=1"]
    # DISARM_DELAY 0: no auto-disarm to be mistaken for the fail-safe.
    common = ["--firmware", "4.7", "--param", "DISARM_DELAY=0", *failsafe]
    ranged = ["--param", "MAV_GCS_SYSID=250", "--param", "MAV_GCS_SYSID_HI=255"]
    with simulator(*common, *ranged) as gcs:  # system 255: inside 250..255
        armed_then_silent(gcs)
        # On the ground ArduCopter says so and disarms (events.cpp).
        first(gcs, "STATUSTEXT", 10, lambda m: m.text == "GCS Failsafe - Disarming")
        first(gcs, "HEARTBEAT", 5, lambda m: not m.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED)
    with simulator(*common, "--param", "MAV_GCS_SYSID=250") as gcs:  # only 250
        armed_then_silent(gcs)
        failsafe_texts = count_until_heartbeats(
            gcs, "STATUSTEXT", 3, lambda m: m.text.startswith("GCS Failsafe")
        )
        assert failsafe_texts == 0
        beat = first(gcs, "HEARTBEAT", 5)
        assert beat.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED


def test_fs_gcs_enable_2_is_named_at_arming_and_its_failsafe_is_rtl_as_arducopter_4():
    """Over the wire: ArduCopter 4.x arms with FS_GCS_ENABLE 2 but names it (its pre-arm
    check), and once the GCS falls silent in flight does RTL (failsafe_gcs_on_event:
    the same case as 1), the heartbeat then saying CRITICAL."""
    args = ["--speedup", "4", "--param", "FS_GCS_ENABLE=2", "--param", "FS_GCS_TIMEOUT=1"]
    with simulator(*args) as gcs:
        assert command(gcs, MAV.MAV_CMD_DO_SET_MODE, 1, 4) == MAV.MAV_RESULT_ACCEPTED
        gcs.mav.command_long_send(1, 1, MAV.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        heard = {}  # the ACK and the pre-arm words, in whichever order they come
        while len(heard) < 2:
            msg = first(gcs, ["STATUSTEXT", "COMMAND_ACK"], 5)
            if msg.get_type() == "COMMAND_ACK" and msg.command == MAV.MAV_CMD_COMPONENT_ARM_DISARM:
                heard["ack"] = msg
            elif msg.get_type() == "STATUSTEXT" and msg.text.startswith("PreArm"):
                heard["prearm"] = msg
        assert heard["ack"].result == MAV.MAV_RESULT_ACCEPTED  # named, not refused
        assert heard["prearm"].text == "PreArm: FS_GCS_ENABLE=2 removed, see FS_OPTIONS"
        assert heard["prearm"].severity == MAV.MAV_SEVERITY_CRITICAL
        gcs.mav.command_long_send(1, 1, MAV.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 6)
        # Heard until it is well up (on the ground the fail-safe would disarm it) ...
        deadline = time.monotonic() + 30
        said = None
        while True:
            gcs.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            msg = first(gcs, ["GLOBAL_POSITION_INT", "STATUSTEXT"], 5)
            if msg.get_type() == "STATUSTEXT":
                if msg.text.startswith("GCS Failsafe"):
                    # A saturated machine let this loop's heartbeats lapse in the climb
                    # (1 s of the autopilot's clock is 0.25 s here): the same fail-safe,
                    # kept by falling silent now (a heartbeat more would clear it).
                    said = msg
                    break
            elif msg.relative_alt > 4000:
                break
            assert time.monotonic() < deadline, "the take-off did not climb"
        # ... then silent.
        if said is None:
            said = first(gcs, "STATUSTEXT", 10, lambda m: m.text.startswith("GCS Failsafe"))
        assert said.text == "GCS Failsafe" and said.severity == MAV.MAV_SEVERITY_WARNING
        beat = first(gcs, "HEARTBEAT", 5, lambda m: m.custom_mode == 6)
        assert beat.system_status == MAV.MAV_STATE_CRITICAL


# --- ArduRover's speed rules -------------------------------------------------------------


def reposition(gcs: Any, north_m: float, *, speed: float = -1) -> int:
    """DO_REPOSITION (COMMAND_INT) ``north_m`` north of home at ``speed`` (-1: none);
    returns its COMMAND_ACK result."""
    lat, lon = offset(BOAT_HOME, north_m, 0.0)
    gcs.mav.command_int_send(
        1, 1, MAV.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, MAV.MAV_CMD_DO_REPOSITION, 0, 0,
        speed, MAV.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, 0,
        round(lat * 1e7), round(lon * 1e7), 0,
    )  # fmt: skip
    ack = first(gcs, "COMMAND_ACK", 5, lambda m: m.command == MAV.MAV_CMD_DO_REPOSITION)
    return int(ack.result)


def test_the_boat_takes_a_speed_only_on_its_way_to_a_position_as_ardurover():
    """ArduRover (Rover/mode_guided.cpp, GCS_MAVLink_Rover.cpp): DO_CHANGE_SPEED, and
    DO_REPOSITION's own speed, which it sets before the position, are FAILED unless
    GUIDED already drives to a position; a boat entering GUIDED holds (loiters)."""
    home = f"{BOAT_HOME[0]},{BOAT_HOME[1]}"
    with simulator("--vehicle-class", "boat", "--home", home) as gcs:
        guided = 15
        assert command(gcs, MAV.MAV_CMD_DO_SET_MODE, 1, guided) == MAV.MAV_RESULT_ACCEPTED
        assert command(gcs, MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1) == MAV.MAV_RESULT_ACCEPTED
        change_speed = MAV.MAV_CMD_DO_CHANGE_SPEED
        assert command(gcs, change_speed, 1, 3, -1) == MAV.MAV_RESULT_FAILED  # holding
        assert reposition(gcs, 100, speed=3) == MAV.MAV_RESULT_FAILED
        assert reposition(gcs, 100) == MAV.MAV_RESULT_ACCEPTED
        assert command(gcs, change_speed, 1, 3, -1) == MAV.MAV_RESULT_ACCEPTED
        assert reposition(gcs, 120, speed=2) == MAV.MAV_RESULT_ACCEPTED  # on its way now
        hold = 4
        assert command(gcs, MAV.MAV_CMD_DO_SET_MODE, 1, hold) == MAV.MAV_RESULT_ACCEPTED
        assert command(gcs, change_speed, 1, 3, -1) == MAV.MAV_RESULT_FAILED


def test_a_stop_before_the_loop_starts_is_not_lost():
    """SIGTERM can come between the simulator's READY line and its loop's first turn
    (a test, or a supervisor, stopping it at once): the loop must not start at all,
    or the process serves on and is killed 5 s later instead of closing its link."""
    pilot = Autopilot(SimOptions(address="udpin:127.0.0.1:0", home=HOME))
    pilot.open()
    try:
        pilot.stop()  # the handler signal.signal installed, as SIGTERM calls it
        runner = threading.Thread(target=pilot.run, daemon=True)
        runner.start()
        runner.join(30)
        assert not runner.is_alive(), "the simulator ran on after it was stopped"
    finally:
        pilot.close()
