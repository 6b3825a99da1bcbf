"""One vehicle on a running platform, as the platform's integration tests drive it: its
rows, and the steps of a session on it, each waited for.

:func:`vehicle_served` makes the rows: a vehicle of one of the types below, offline at a
station of its own until its agent registers, the service whose sessions control it,
and the credential its agent dials in with (:func:`car_served` for a car). The steps
(:func:`agent_registered`, :func:`session_deployed`, :func:`session_active`,
:func:`unintentional_end_recorded`) return once the platform or the agent shows that
they happened.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import urllib.error
import urllib.request
from collections.abc import AsyncIterator
from typing import Any

from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from agents.runtime import Agent
from fleet.credentials import vehicle_issue_credential
from fleet.models import Vehicle
from services.models import Service, Session
from services.sessions.deployment import UserTask
from tests import factories as f
from tests.control import command, recv
from tests.deployment import session_requested
from tests.servers import agent_running, cancelled, db, until

#: The vehicle types, as (kind, adapter, name).
CAR = ("ground", "car", "Raspberry Pi car")
QUADCOPTER = ("aerial", "mavlink", "MAVLink quadcopter")
VTOL = ("hybrid", "spektrum", "Spektrum VTOL plane")

#: Every command of the car's adapter.
CAR_COMMANDS = ["forward", "backward", "left", "right", "stop", "camera_up", "camera_down"]


def vehicle_served(
    name: str,
    vtype: tuple[str, str, str],
    *,
    service: str,
    commands: list[str],
    failsafe_action: str,
    min_battery: int | None = 20,
    link_loss_timeout_ms: int = 500,
    attributes: dict[str, Any] | None = None,
    **service_fields: Any,
) -> tuple[Vehicle, str, Service]:
    """Vehicle ``name`` of type ``vtype`` (:data:`CAR`...), offline at a new station,
    with ``attributes`` (tests.factories.vehicle's); the service of slug ``service``
    whose one role takes a vehicle of that kind (with ``min_battery`` % at least, unless
    None), allowing ``commands``, with ``failsafe_action`` after
    ``link_loss_timeout_ms`` and ``service_fields``; and the vehicle's credential."""
    kind, adapter, type_name = vtype
    vehicle = f.vehicle(
        station=f.station(),
        vtype=f.vehicle_type(kind, adapter, name=type_name),
        name=name,
        online=False,
        **(attributes or {}),
    )
    role: dict[str, Any] = {"name": "vehicle", "kinds": [kind]}
    if min_battery is not None:
        role["min_battery"] = min_battery
    served = f.service(
        service,
        roles=[role],
        allowed_commands=commands,
        failsafe_action=failsafe_action,
        link_loss_timeout_ms=link_loss_timeout_ms,
        **service_fields,
    )
    return vehicle, vehicle_issue_credential(vehicle=vehicle), served


def car_served(
    name: str,
    *,
    service: str,
    commands: list[str] | None = None,
    features: list[str] | None = None,
    **options: Any,
) -> tuple[Vehicle, str, Service]:
    """:func:`vehicle_served` for a :data:`CAR` on land, with ``features``, whose
    service allows ``commands`` (default :data:`CAR_COMMANDS`) and stops it on a
    fail-safe; ``options`` are vehicle_served's."""
    attributes: dict[str, Any] = {"environments": ["land"]}
    if features is not None:
        attributes["features"] = features
    return vehicle_served(
        name,
        CAR,
        service=service,
        commands=CAR_COMMANDS if commands is None else commands,
        failsafe_action="stop",
        attributes=attributes,
        **options,
    )


async def agent_registered(
    vehicle: Vehicle, *, within: float = 10, positioned: bool = False
) -> Vehicle:
    """Wait until ``vehicle``'s agent has registered: the vehicle idle with its control
    URL (and with a position, if ``positioned``). Returns the vehicle's row then."""

    async def registered() -> Vehicle | None:
        v = await db(Vehicle.objects.get, pk=vehicle.pk)
        done = v.status == Vehicle.Status.IDLE and bool(v.control_url)
        return v if done and (v.lat is not None or not positioned) else None

    where = " with a position" if positioned else ""
    return await until(registered, within=within, what=f"the agent to register{where}")


async def session_deployed(
    agent: Agent, service: Service, *, username: str = "alice"
) -> tuple[Session, UserTask]:
    """A new client ``username``'s session of ``service`` towards tests.factories.HOME,
    requested and deployed; returned, with its user task, once the task has reached
    ``agent``."""
    user = await db(f.user, username)
    opened = await db(session_requested, user=user, service=service, target=f.HOME)
    session, user_task = opened.session, opened.task
    assert user_task is not None

    async def task_arrived() -> bool:
        return agent.hub is not None and agent.hub.task is not None

    await until(task_arrived, what="the task to reach the agent")
    return session, user_task


async def session_active(session: Session) -> None:
    """Wait until the platform has seen the session's user connect (it is active)."""

    async def active() -> bool:
        s = await db(Session.objects.get, pk=session.pk)
        return s.state == Session.State.ACTIVE

    await until(active, what="the platform to see the user connected")


async def unintentional_end_recorded(session: Session) -> list[tuple[str, dict[str, Any]]]:
    """Wait until the session's log records an unintentional end; returns the log as
    (kind, data) pairs."""

    async def recorded() -> list[tuple[str, dict[str, Any]]]:
        events = await db(
            lambda: list(Session.objects.get(pk=session.pk).events.values_list("kind", "data"))
        )
        return events if any(kind == "unintentional_end" for kind, _ in events) else []

    return await until(recorded, what="the platform to record the unintentional end")


# --- a car session through the API, driven over the agent's own socket -------------------


def api(base: str, method: str, path: str, token: str, body: Any = None) -> tuple[int, Any]:
    """Call the JSON API; returns (status, body)."""
    request = urllib.request.Request(
        f"{base}/api/v1{path}",
        method=method,
        data=json.dumps(body).encode() if body is not None else None,
        headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
    )
    try:
        with urllib.request.urlopen(request, timeout=20) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def car_agent(base: str, car: Vehicle, credential: str) -> Any:
    """The car's agent, in this process, on its simulator (an async context manager)."""
    return agent_running(
        base=base,
        vehicle=car,
        credential=credential,
        adapter="car",
        options={"origin": list(f.HOME)},
    )


async def request_car(base: str, token: str) -> dict[str, Any]:
    """The 201 body of a request for the car service through the API."""
    status, body = await asyncio.to_thread(
        api, base, "POST", "/sessions", token, {"service": "drive-car"}
    )
    assert status == 201, body
    return body


async def drive(task: dict[str, Any], seq: int) -> Any:
    """Connect to the vehicle with the user task once its agent has accepted the
    session's task (as the controller page does by retrying), and drive once."""
    session_id = task["session_id"]

    async def accepted() -> bool:
        return await db(
            lambda: Session.objects.get(pk=session_id).events.filter(kind="task_accepted").exists()
        )

    await until(accepted, within=15, what="the agent to accept its task")
    ws = await connect(task["control_url"], proxy=None, compression=None)
    await ws.send(json.dumps({"type": "auth", "grant": task["grant"]}))
    assert (await recv(ws, "welcome"))["role"] == "controller"
    assert (await command(ws, seq, "forward", speed=0.5))["ok"]
    return ws


@contextlib.asynccontextmanager
async def controller_present(ws: Any) -> AsyncIterator[None]:
    """The controller on ``ws`` stays present, as an open page does: a keepalive every
    100 ms while the block runs (until the vehicle closes the socket). Without them the
    vehicle's link-loss fail-safe acts after its timeout, and the session then ends for
    that, whatever the test meant to break."""

    async def beat() -> None:
        with contextlib.suppress(ConnectionClosed):
            while True:
                await ws.send(json.dumps({"type": "keepalive"}))
                await asyncio.sleep(0.1)

    task = asyncio.create_task(beat())
    try:
        yield
    finally:
        await cancelled(task)
