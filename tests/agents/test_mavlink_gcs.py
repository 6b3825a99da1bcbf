"""Third-party conformance: an independent ground station from PyPI flies the simulator.

MAVSDK is a C++ MAVLink implementation (no pymavlink inside): ``mavsdk-grpc`` ships the
``mavsdk_server`` binary and drives it over gRPC. If the simulator's heartbeats, mode
numbers, COMMAND_ACKs, AUTOPILOT_VERSION or streams were off, MAVSDK would not connect,
arm, take off or report the altitude. (``mavsdk`` 4.x is a different, native binding;
``mavsdk<4`` is the same gRPC API under the old name.)
"""

from __future__ import annotations

import asyncio
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from tests.agents.mavlink_rig import HOME, ROOT

mavsdk = pytest.importorskip("mavsdk_grpc", reason="needs mavsdk-grpc (MAVSDK with mavsdk_server)")
# Importing mavsdk_grpc makes uvloop the event loop policy of the whole process, and
# every xdist worker imports it while collecting: every later test then ran on uvloop,
# which the agents do not use. On Python 3.12 that hung a worker: uvloop's fork for a
# subprocess runs Python's after-fork clean-up in the child, which freed another
# thread's PyAV scaler there and waited for ever on that thread's lock. Back to
# asyncio's own policy, for this module too (MAVSDK runs on any loop).
asyncio.set_event_loop_policy(None)


def _free_port(kind: socket.SocketKind) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _simulator(udp: int) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [
            sys.executable, "-m", "agents", "sim", "mavlink",
            "--connect", f"udpout:127.0.0.1:{udp}",
            "--home", f"{HOME[0]},{HOME[1]}",
            "--speedup", "3",
        ],
        cwd=ROOT, stdout=subprocess.DEVNULL,
    )  # fmt: skip


@pytest.fixture
async def flown() -> AsyncIterator[tuple[Any, subprocess.Popen[bytes]]]:
    """MAVSDK listening on a UDP port, the simulator sending to it; both stopped after."""
    server = Path(mavsdk.__file__).parent / "bin" / "mavsdk_server"
    if not server.exists():
        pytest.skip(f"mavsdk_server is not shipped for this platform ({sys.platform})")
    udp, grpc_port = _free_port(socket.SOCK_DGRAM), _free_port(socket.SOCK_STREAM)
    sim = _simulator(udp)
    drone = mavsdk.System(port=grpc_port)
    try:
        await asyncio.wait_for(drone.connect(system_address=f"udpin://127.0.0.1:{udp}"), 20)
        yield drone, sim
    finally:
        drone._stop_mavsdk_server()
        sim.terminate()
        try:
            sim.wait(5)
        except subprocess.TimeoutExpired:
            sim.kill()
            sim.wait()


async def _first(stream: Any, predicate: Any, within: float) -> Any:
    async def scan() -> Any:
        async for value in stream:
            if predicate(value):
                return value
        return None

    return await asyncio.wait_for(scan(), within)


async def test_mavsdk_connects_arms_takes_off_and_reads_the_altitude(flown):
    drone, sim = flown
    state = await _first(drone.core.connection_state(), lambda s: s.is_connected, 20)
    assert state.is_connected
    info = await asyncio.wait_for(drone.info.get_version(), 10)
    assert (info.flight_sw_major, info.flight_sw_minor) == (4, 5)  # AUTOPILOT_VERSION

    # MAVSDK asks for the position stream with SET_MESSAGE_INTERVAL.
    await drone.telemetry.set_rate_position(10.0)
    await drone.action.set_takeoff_altitude(3.0)
    await drone.action.arm()
    assert await _first(drone.telemetry.armed(), lambda armed: armed, 5)
    started = time.monotonic()
    await drone.action.takeoff()
    position = await _first(drone.telemetry.position(), lambda p: p.relative_altitude_m > 2.8, 15)
    assert position.relative_altitude_m < 3.3
    assert abs(position.latitude_deg - HOME[0]) < 1e-4
    assert abs(position.longitude_deg - HOME[1]) < 1e-4
    assert time.monotonic() - started < 10

    await drone.action.land()
    assert await _first(drone.telemetry.armed(), lambda armed: not armed, 20) is False
    assert sim.poll() is None  # the simulator survived a foreign ground station
