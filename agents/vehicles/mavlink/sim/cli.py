"""``python -m agents sim mavlink``: a simulated ArduPilot vehicle on a MAVLink link.

``python -m agents sim mavlink --listen udpin:127.0.0.1:14550 --home LAT,LON`` serves a
simulated ArduCopter quadcopter; ``--vehicle-class boat`` an ArduRover boat
(FRAME_CLASS 2). Point the agent's mavlink adapter, MAVProxy, MAVSDK or QGroundControl
at it. :func:`cli` prints ``READY <address>`` once the link is open.
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
from collections.abc import Iterable

from agents.vehicles.mavlink.classes import VEHICLE_CLASSES
from agents.vehicles.mavlink.sim.autopilot import (
    DEFAULT_STREAM_RATE_HZ,
    VEHICLES,
    Autopilot,
    SimOptions,
)
from agents.vehicles.mavlink.sim.params import (
    DEFAULT_FIRMWARE,
    FIRMWARES,
    KNOWN_PARAMS,
    firmware_params,
)

#: Where a vehicle sits at start (AMSL, m) unless ``--home-alt`` says otherwise: a
#: copter's field, a boat's sea level.
HOME_ALT_M = {"copter": 50.0, "boat": 0.0}


def _latlon(text: str) -> tuple[float, float]:
    try:
        lat_s, lon_s = text.split(",")
        lat, lon = float(lat_s), float(lon_s)
    except ValueError:
        raise argparse.ArgumentTypeError("expected LAT,LON in degrees") from None
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise argparse.ArgumentTypeError("latitude or longitude out of range")
    return lat, lon


def _param(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    if not sep or name.strip().upper() not in KNOWN_PARAMS:
        raise argparse.ArgumentTypeError(
            f"expected NAME=VALUE with NAME one of {', '.join(sorted(KNOWN_PARAMS))}"
        )
    try:
        return name.strip().upper(), float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{name}: not a number") from None


def _positive(text: str) -> float:
    value = float(text)
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError("must be a positive number")
    return value


def _current(text: str) -> tuple[float, float]:
    try:
        speed_s, towards_s = text.split(",")
        speed, towards = float(speed_s), float(towards_s)
    except ValueError:
        raise argparse.ArgumentTypeError("expected SPEED,TOWARDS: m/s and degrees") from None
    if not (0 <= speed <= 5 and math.isfinite(towards)):
        raise argparse.ArgumentTypeError("the speed must be within 0..5 m/s")
    return speed, towards


def parse_args(argv: Iterable[str]) -> SimOptions:
    """Parse the command line into :class:`~.autopilot.SimOptions` (argparse exits on
    errors, naming the option)."""
    parser = argparse.ArgumentParser(
        prog="python -m agents sim mavlink",
        description="Simulated ArduPilot vehicle, an ArduCopter quadcopter or an ArduRover "
        "boat (MAVLink 2 over UDP, TCP or serial). Point the agent's mavlink adapter, "
        "MAVProxy, MAVSDK or QGroundControl at it.",
    )
    where = parser.add_mutually_exclusive_group()
    where.add_argument(
        "--listen",
        help="wait for ground stations: udpin:HOST:PORT (port 0: any free one) or "
        "tcpin:HOST:PORT (default udpin:127.0.0.1:14550)",
    )
    where.add_argument(
        "--connect",
        help="reach a ground station: udpout:HOST:PORT, tcp:HOST:PORT or a serial device "
        "as DEVICE[,BAUD]",
    )
    parser.add_argument(
        "--vehicle-class",
        choices=tuple(VEHICLES),
        default="copter",
        help="copter: ArduCopter (a quadcopter); boat: ArduRover with FRAME_CLASS 2, kept "
        "on water by the packaged land mask",
    )
    parser.add_argument("--home", type=_latlon, default=(40.6306, -8.6588), help="LAT,LON")
    parser.add_argument(
        "--home-alt", type=float, default=None, help="home altitude AMSL, m (copter 50, boat 0)"
    )
    parser.add_argument("--heading", type=float, default=0.0, help="initial heading, degrees")
    parser.add_argument("--speedup", type=_positive, default=1.0, help="flight time factor")
    parser.add_argument("--battery", type=float, default=100.0, help="initial charge, percent")
    parser.add_argument(
        "--drain", type=float, default=5.0, help="battery drain at full effort, percent per minute"
    )
    parser.add_argument("--gps", choices=("3d", "2d", "none"), default="3d", help="GPS fix")
    parser.add_argument("--satellites", type=int, default=12)
    parser.add_argument(
        "--gps-fix-after",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="the GPS gets its fix this long after the start (wall clock): until then no "
        "fix, 0 satellites and position 0/0, as ArduPilot before its EKF origin is set",
    )
    parser.add_argument(
        "--firmware",
        choices=tuple(FIRMWARES),
        default=DEFAULT_FIRMWARE,
        help="the ArduPilot release simulated: its version and parameter names (4.7 has "
        "MAV_GCS_SYSID, MAV_GCS_SYSID_HI and MAV_SYSID instead of SYSID_MYGCS and "
        "SYSID_THISMAV, and ArduRover its FS_GCS_TIMEOUT)",
    )
    parser.add_argument("--sysid", type=int, default=1, help="MAVLink system id")
    parser.add_argument(
        "--param", type=_param, action="append", default=[], help="NAME=VALUE (repeatable)"
    )
    parser.add_argument(
        "--stream-rate",
        type=float,
        default=DEFAULT_STREAM_RATE_HZ,
        help="every telemetry stream's rate (Hz) until a ground station asks otherwise, "
        "like ArduPilot's SRn_ parameters; default 1 (ArduPlane's and ArduRover's default), "
        "0: only the streams a ground station asks for (ArduCopter's default)",
    )
    parser.add_argument(
        "--current",
        type=_current,
        default=(0.0, 0.0),
        metavar="SPEED,TOWARDS",
        help="a boat's water current: m/s, and the direction it flows towards in degrees "
        "(a boat in HOLD drifts with it; LOITER holds against it)",
    )
    parser.add_argument("--parent-pid", type=int, default=None, help="stop when it exits")
    parser.add_argument("--log-level", default="WARNING")
    args = parser.parse_args(list(argv))
    if not 0 <= args.battery <= 100:
        parser.error("--battery must be within 0..100")
    if not 1 <= args.sysid <= 254:
        parser.error("--sysid must be within 1..254")
    if not (math.isfinite(args.gps_fix_after) and args.gps_fix_after >= 0):
        parser.error("--gps-fix-after must be 0 or more seconds")
    vehicle = args.vehicle_class
    if args.current != (0.0, 0.0) and vehicle != "boat":
        parser.error("--current is a boat's (--vehicle-class boat)")
    params = dict(args.param)
    unknown = set(params) - set(firmware_params(args.firmware, vehicle))
    if unknown:
        firmware = VEHICLE_CLASSES[vehicle].firmware
        parser.error(
            f"{firmware} {args.firmware} has no parameter {', '.join(sorted(unknown))} "
            "(see --firmware and --vehicle-class)"
        )
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    return SimOptions(
        address=args.connect or args.listen or "udpin:127.0.0.1:14550",
        home=args.home,
        vehicle=vehicle,
        home_alt_amsl=HOME_ALT_M[vehicle] if args.home_alt is None else args.home_alt,
        heading_deg=args.heading,
        speedup=args.speedup,
        battery_pct=args.battery,
        drain_pct_per_min=max(0.0, args.drain),
        gps_fix={"3d": 3, "2d": 2, "none": 0}[args.gps],
        satellites=max(0, args.satellites) if args.gps != "none" else 0,
        sysid=args.sysid,
        params=params,
        parent_pid=args.parent_pid,
        stream_rate_hz=max(0.0, args.stream_rate),
        gps_fix_after_s=args.gps_fix_after,
        firmware=args.firmware,
        current=args.current,
    )


def cli(argv: list[str]) -> int:
    """``python -m agents sim mavlink``: serve a simulated vehicle until stopped.

    Prints ``READY <address>`` on stdout once the link is open (with the actual port for
    ``udpin:HOST:0``). Returns 0 when stopped (Ctrl-C, SIGTERM or the ``--parent-pid``
    process gone), 2 when the link cannot be opened.
    """
    options = parse_args(argv)
    pilot = Autopilot(options)
    try:
        address = pilot.open()
    except Exception as exc:
        print(f"cannot open {options.address}: {exc}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, pilot.stop)
    print(f"READY {address}", flush=True)
    try:
        pilot.run()
    except KeyboardInterrupt:
        pass
    finally:
        pilot.close()
    return 0
