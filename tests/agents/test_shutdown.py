"""The agent stopped by its service manager: SIGTERM (systemd, container runtimes) and
SIGINT (Ctrl-C) alike make the vehicle perform the task's fail-safe action.

A real deployment's processes: the simulated ArduCopter on its own
(``python -m agents sim mavlink``), the agent on it (``python -m agents run``, as on a
vehicle), a stand-in platform that gives it a task, a browser's controller that flies
it, and a second ground station that watches the autopilot's mode. The task's action is
``land`` (the adapter's own ``close_action`` is ``return_to_home``): the autopilot must
land, not return. The task's ceiling, handed to the autopilot's fence at its start,
stays there: the agent is gone.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from datetime import datetime
from pathlib import Path

import pytest
from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve

from agents.protocol import (
    PROTOCOL_VERSION,
    generate_keypair,
    load_private_key,
)
from agents.vehicles.mavlink.dialect import MAV
from tests.agents.documents import grant_for, task_for
from tests.agents.mavlink_rig import (
    HOME,
    ROOT,
    ground_station,
    modes_until,
    simulator_listening,
    watch,
)
from tests.agents.waiting import until
from tests.control import command, recv

PRIVATE_PEM, PUBLIC_PEM = generate_keypair()
PRIVATE = load_private_key(PRIVATE_PEM)
VEHICLE = "quad-shutdown-1"
SESSION = "session-shutdown"
COMMANDS = ("take_off", "up", "front", "land", "return_to_home", "stop")
LAND, RTL = 9, 6


class Platform:
    """Welcomes the agent, gives it one task, and keeps what it reports."""

    def __init__(self, token: str) -> None:
        self.token = token
        self.port = 0
        self.control_url: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        self.accepted = asyncio.Event()
        self.events: list[str] = []

    async def handler(self, ws: ServerConnection) -> None:
        hello = json.loads(await ws.recv())
        assert hello["type"] == "hello"
        await ws.send(
            json.dumps({"type": "welcome", "v": PROTOCOL_VERSION, "heartbeat_interval_s": 30})
        )
        await ws.send(json.dumps({"type": "task", "id": "task-1", "token": self.token}))
        with contextlib.suppress(Exception):
            async for raw in ws:
                msg = json.loads(raw)
                if msg["type"] == "profile" and not self.control_url.done():
                    self.control_url.set_result(msg["control_url"])
                elif msg["type"] == "task_accepted":
                    self.accepted.set()
                elif msg["type"] == "event":
                    self.events.append(msg["event"])


def make_task() -> str:
    return task_for(
        VEHICLE,
        COMMANDS,
        session=SESSION,
        ttl=300,
        link_loss_timeout_ms=2000,
        failsafe_action="land",
        max_altitude_m=30,
    ).sign(PRIVATE)


def make_grant() -> str:
    return grant_for(VEHICLE, COMMANDS, PRIVATE, session=SESSION, ttl=300)


@contextlib.asynccontextmanager
async def simulator() -> AsyncIterator[str]:
    """The simulated ArduCopter (4x flight time, GCS fail-safe off: only the agent acts)
    on a free port; yields the address to reach it."""
    with simulator_listening("--home", f"{HOME[0]},{HOME[1]}", "--speedup", "4") as (_, address):
        yield address


def agent_config(folder: Path, platform_port: int, autopilot: str) -> Path:
    path = folder / "agent.json"
    path.write_text(
        json.dumps(
            {
                "platform_url": f"ws://127.0.0.1:{platform_port}",
                "vehicle_id": VEHICLE,
                "credential": "c",
                "platform_public_key": PUBLIC_PEM,
                "adapter": "mavlink",
                "adapter_options": {"connection": autopilot, "close_action": "return_to_home"},
                "reconnect_min_s": 0.1,
                "reconnect_max_s": 0.5,
            }
        )
    )
    return path


def start_agent(config: Path, log_path: Path) -> subprocess.Popen[bytes]:
    """``python -m agents run --config CONFIG``, as on a vehicle, its log in a file."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with log_path.open("w") as log_file:
        return subprocess.Popen(
            [sys.executable, "-m", "agents", "run", "--config", str(config)],
            cwd=ROOT, env=env, stdout=log_file, stderr=subprocess.STDOUT,
        )  # fmt: skip


def logged_at(line: str) -> float:
    """The wall-clock time of one of the agent's log lines."""
    stamp = re.match(r"(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3})", line)
    assert stamp, line
    return datetime.strptime(stamp.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp()


async def modes_seen(address: str, until: int, within: float) -> tuple[list[int], float]:
    """The autopilot's modes as another ground station (system 200) sees them in its
    heartbeats, until ``until`` shows; and its FENCE_ENABLE then."""
    with ground_station(address) as observer:
        modes = await modes_until(
            observer, until=until, within=within, vehicle_type=MAV.MAV_TYPE_QUADROTOR
        )
        observer.mav.param_request_read_send(1, 1, b"FENCE_ENABLE", -1)
        value = await asyncio.to_thread(
            observer.recv_match, type="PARAM_VALUE", blocking=True, timeout=5
        )
    return modes, -1.0 if value is None else float(value.param_value)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
async def test_a_stopped_agent_leaves_the_vehicle_doing_the_tasks_safe_action(
    tmp_path: Path, signum: signal.Signals
) -> None:
    platform = Platform(make_task())
    async with (
        simulator() as autopilot,
        serve(platform.handler, "127.0.0.1", 0) as server,
    ):
        platform.port = next(iter(server.sockets)).getsockname()[1]
        config = agent_config(tmp_path, platform.port, autopilot)
        log_path = tmp_path / "agent.log"
        agent = start_agent(config, log_path)
        try:
            control_url = await asyncio.wait_for(platform.control_url, 30)
            await asyncio.wait_for(platform.accepted.wait(), 10)
            ws = await connect(control_url, compression=None, proxy=None)
            await ws.send(json.dumps({"type": "auth", "grant": make_grant()}))
            assert (await recv(ws, "welcome"))["role"] == "controller"
            await ws.send(json.dumps({"type": "subscribe", "topics": ["altitude"], "rate_hz": 10}))
            # The task's ceiling goes to the autopilot's fence as the task starts (a
            # second or so of parameter writes): in place before the flight.
            await until(
                lambda: "autopilot_fence_set" in platform.events,
                within=15,
                what="the autopilot's fence set from the task",
            )
            assert (await command(ws, 1, "take_off", altitude_m=6))["ok"]
            await watch(ws, lambda d: (d["altitude"] or 0) > 5, 20, "6 m")
            signalled = time.time()
            agent.send_signal(signum)
            modes, fence = await modes_seen(autopilot, LAND, 15)
            code = await asyncio.to_thread(agent.wait, 30)
        finally:
            if agent.poll() is None:
                agent.kill()
                agent.wait()
    log = log_path.read_text()
    assert code == 0, log
    assert LAND in modes and RTL not in modes, (modes, log)
    # The autopilot's fence, set at the task's start, stays on through the shutdown.
    assert fence == 1
    [done] = [line for line in log.splitlines() if "shutdown: land under way" in line]
    took = logged_at(done) - signalled
    print(f"\n{signum.name} in flight: the task's land acknowledged {took * 1000:.0f} ms later")
    # The agent's own account (its log's clock), not the test's scheduling.
    assert took < 1.0, log
