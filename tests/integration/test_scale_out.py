"""Scale-out: two platform processes behind one address, sharing PostgreSQL and Redis.

nginx (``benchmarks.nginx_proxy``) sends the agents' uplinks (``/ws/agent/``) to process
A and everything else (the API, the relay) to process B. A session requested on B is
assigned there, its task reaches the agent connected to A, a relayed control session
opened on B drives the car through A, and supervision holds across the two: the
controller's socket dying on B makes the agent on A stop and the platform log it, and a
monitor's stop on B revokes the agent on A. nginx's access log shows that each process
served only its own share.
"""

from __future__ import annotations

import asyncio
import json
import urllib.request
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import pytest
from websockets.asyncio.client import connect

from accounts.roles import MONITOR
from accounts.tokens import token_issue
from agents.runtime import Agent
from benchmarks.nginx_proxy import (
    AccessEntry,
    Backend,
    NginxProxy,
    NginxUnavailable,
    Routes,
    Rule,
    nginx_binary,
)
from fleet.models import Vehicle
from services.models import Session
from tests import factories as f
from tests.control import command, recv
from tests.servers import agent_running, db, platform_process, until
from tests.vehicles import car_served

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
]
CAR_COMMANDS = ["forward", "backward", "left", "right", "stop"]


@dataclass
class World:
    car: Vehicle
    credential: str
    client_token: str
    monitor_token: str


def _world() -> World:
    car, credential, _ = car_served(
        "car-1", service="drive-car", commands=CAR_COMMANDS, min_battery=None
    )
    return World(
        car=car,
        credential=credential,
        client_token=token_issue(user=f.user("alice"), name="test"),
        monitor_token=token_issue(user=f.user("mona", roles=(MONITOR,)), name="test"),
    )


def _port(base: str) -> int:
    return int(base.rsplit(":", 1)[1])


async def _api(base: str, token: str, path: str, body: dict[str, Any] | None = None) -> Any:
    """POST ``body`` to the API at ``base``; the parsed answer (raises on an HTTP error)."""

    def call() -> Any:
        request = urllib.request.Request(
            f"{base}{path}",
            data=json.dumps(body or {}).encode(),
            headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
            method="POST",
        )
        with urllib.request.urlopen(request, timeout=30) as response:
            return json.loads(response.read())

    return await asyncio.to_thread(call)


@dataclass
class Platform:
    front: str  # the proxy's base URL, the only address anyone uses
    agents_process: str  # A
    users_process: str  # B
    proxy: NginxProxy


@pytest.fixture
async def platform() -> AsyncIterator[Platform]:
    try:
        nginx_binary()  # Debian's, installed if missing
    except NginxUnavailable as exc:
        pytest.skip(f"needs nginx: {exc}")
    with platform_process() as a, platform_process() as b:
        routes = Routes(
            default=Backend("127.0.0.1", _port(b)),
            rules=[Rule("/ws/agent/", Backend("127.0.0.1", _port(a)))],
        )
        async with NginxProxy(routes) as proxy:
            yield Platform(f"http://127.0.0.1:{proxy.port}", a, b, proxy)


async def _log_kinds(session_id: str) -> list[str]:
    return await db(
        lambda: list(
            Session.objects.get(pk=session_id).events.order_by("seq").values_list("kind", flat=True)
        )
    )


async def test_two_processes_assign_deploy_relay_and_supervise(platform: Platform) -> None:
    world = await db(_world)
    async with agent_running(
        base=platform.front,
        vehicle=world.car,
        credential=world.credential,
        adapter="car",
        options={"origin": [f.HOME[0], f.HOME[1]]},
    ) as agent:
        await _drive_across_processes(platform, world, agent)

    # Each process served only its share, A the uplink, B the API and the relay: nginx
    # logs the process that served each request (a WebSocket once it ended).
    agents_at = f"127.0.0.1:{_port(platform.agents_process)}"
    users_at = f"127.0.0.1:{_port(platform.users_process)}"

    async def logged() -> list[AccessEntry]:
        entries = platform.proxy.requests()
        paths = " ".join(entry.uri for entry in entries)
        return entries if "/ws/agent/" in paths and "/ws/relay/" in paths else []

    entries = await until(logged, what="nginx to log the uplink and the relayed socket")
    for entry in entries:
        assert entry.upstream == (agents_at if entry.uri.startswith("/ws/agent/") else users_at)
    # The session request and the monitor's stop.
    assert sum(entry.uri.startswith("/api/v1/sessions") for entry in entries) == 2


async def _drive_across_processes(platform: Platform, world: World, agent: Agent) -> None:
    async def registered() -> bool:
        car = await db(Vehicle.objects.get, pk=world.car.pk)
        return car.status == Vehicle.Status.IDLE and bool(car.control_url)

    await until(registered, within=20, what="the agent to register through process A")

    # Requested and assigned on B; the task goes to the agent's uplink on A.
    created = await _api(
        platform.front,
        world.client_token,
        "/api/v1/sessions",
        {"service": "drive-car", "relay": True, "target": {"lat": f.HOME[0], "lon": f.HOME[1]}},
    )
    sid, task = created["session"]["id"], created["task"]
    assert created["session"]["state"] == "assigned"
    assert task["vehicle_id"] == str(world.car.pk)
    assert task["control_url"] == f"{platform.front.replace('http', 'ws')}/ws/relay/{sid}/"

    async def accepted() -> bool:
        return "task_accepted" in await _log_kinds(sid)

    await until(accepted, what="task_accepted from the agent on A in the session log")
    assert agent.hub is not None and agent.hub.task is not None
    assert agent.hub.task.session_id == sid

    # A relayed controller on B drives the car on A and gets acks.
    ws = await connect(task["control_url"], proxy=None, compression=None)
    await ws.send(json.dumps({"type": "auth", "grant": task["grant"]}))
    assert (await recv(ws, "welcome"))["role"] == "controller"
    assert (await command(ws, 7, "forward", speed=1.0)) == {
        "type": "ack",
        "seq": 7,
        "ok": True,
        "error": None,
    }

    async def active() -> bool:
        session = await db(Session.objects.get, pk=sid)
        return session.state == Session.State.ACTIVE

    await until(active, what="the session to become active (user_connected, logged by A)")
    motors = agent.adapter.telemetry()["motors"]
    assert motors != {"left": 0.0, "right": 0.0}

    # The controller's socket dies on B: the agent on A stops, the platform logs it.
    ws.transport.abort()

    async def stopped() -> bool:
        return bool(agent.adapter.telemetry()["motors"] == {"left": 0.0, "right": 0.0})

    await until(stopped, within=5, what="the car to stop after the relayed link died")

    async def failsafe_logged() -> bool:
        return "unintentional_end" in await _log_kinds(sid)

    await until(failsafe_logged, what="the fail-safe in the session log")

    # A monitor's stop on B revokes the agent on A.
    stopped_session = await _api(
        platform.front, world.monitor_token, f"/api/v1/sessions/{sid}/stop", {"reason": "drill"}
    )
    assert stopped_session["state"] == "aborted"

    async def revoked() -> bool:
        return agent.hub is not None and agent.hub.task is None

    await until(revoked, what="the revoke to reach the agent on A")

    async def ended_logged() -> bool:
        return "task_ended" in await _log_kinds(sid)

    await until(ended_logged, what="the agent's task_ended in the session log")
    kinds = await _log_kinds(sid)
    assert kinds.index("task_deployed") < kinds.index("task_accepted")
    assert kinds.index("user_connected") < kinds.index("unintentional_end")
