"""Redis restarted under a running platform: the relay (and WebRTC signalling, which
rides it) answers every connected vehicle again within 5 s, without restarting any
agent.

Real servers: the platform under its server on a redis-server of this test's own (it is
killed and started again; the machine's shared one must stay up for everyone else),
PostgreSQL, and two cars' agents on their simulators, connected before the restart. A
restarted Redis keeps nothing (no persistence): the vehicles' channel-layer groups are
gone, and the uplinks must be back in them (fleet.memberships) for a new relayed
connection's authentication to reach its vehicle.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from typing import Any

import pytest
from websockets.asyncio.client import connect

from accounts.tokens import token_issue
from fleet.credentials import vehicle_issue_credential
from fleet.models import Vehicle
from services.models import Session
from tests import factories as f
from tests.control import recv
from tests.servers import db, platform_process, redis_server_process, until
from tests.vehicles import agent_registered, api, car_agent, car_served

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.realtime,
    pytest.mark.django_db(transaction=True),
]

#: How long Redis stays away: a restart (a process that loads nothing comes back at once).
OUTAGE_S = 2.0
#: The longest a relayed user may wait once Redis answers again (the issue's bound).
ANSWER_AGAIN_S = 5.0


def _fleet() -> tuple[list[Vehicle], list[str]]:
    """Two cars at one station, both matching the drive-car service, with their
    agents' credentials."""
    car, credential, _service = car_served("car-1", service="drive-car")
    other = f.vehicle(
        station=car.station, vtype=car.vehicle_type, name="car-2", online=False, **car.attributes
    )
    return [car, other], [credential, vehicle_issue_credential(vehicle=other)]


async def _session_requested(base: str, token: str) -> dict[str, Any]:
    """A drive-car session through the API, once its vehicle's agent accepted the task;
    returns the user task (session id, vehicle id, grant)."""
    status, body = await asyncio.to_thread(
        api, base, "POST", "/sessions", token, {"service": "drive-car"}
    )
    assert status == 201, body
    task: dict[str, Any] = body["task"]

    async def accepted() -> bool:
        return await db(
            lambda: (
                Session.objects.get(pk=task["session_id"])
                .events.filter(kind="task_accepted")
                .exists()
            )
        )

    await until(accepted, within=15, what="the agent to accept its task")
    return task


async def _fresh_grant(base: str, token: str, session_id: str) -> str:
    status, body = await asyncio.to_thread(
        api, base, "POST", f"/sessions/{session_id}/grant", token
    )
    assert status == 200, body
    grant: str = body["task"]["grant"]
    return grant


async def _relayed_command(base: str, session_id: str, grant: str, seq: int, within: float) -> None:
    """Connect to the session's relay as the controller page does, authenticate with
    ``grant`` and have one command acknowledged; raises if any step fails or takes
    longer than ``within`` seconds in all."""
    url = f"{base.replace('http', 'ws')}/ws/relay/{session_id}/"
    deadline = time.monotonic() + within

    def left() -> float:
        return max(0.05, deadline - time.monotonic())

    async with asyncio.timeout(within):
        ws = await connect(url, proxy=None, compression=None)
        try:
            await ws.send(json.dumps({"type": "auth", "grant": grant}))
            assert (await recv(ws, "welcome", within=left()))["role"] == "controller"
            await ws.send(json.dumps({"type": "command", "seq": seq, "name": "forward",
                                      "args": {"speed": 0.3}}))  # fmt: skip
            ack = await recv(ws, "ack", within=left())
            assert ack["seq"] == seq and ack["ok"], ack
        finally:
            await ws.close()


async def _answered_again(
    base: str, token: str, session_id: str, *, since: float, tries: list[str]
) -> float:
    """Seconds from ``since`` until a new relayed connection of the session drove its
    vehicle, trying again with a fresh grant (as the page does) until
    :data:`ANSWER_AGAIN_S` have passed; each failed try is added to ``tries``. Raises
    AssertionError when none succeeded in time."""
    seq = 100
    while (left := since + ANSWER_AGAIN_S - time.monotonic()) > 0:
        seq += 1
        try:
            grant = await _fresh_grant(base, token, session_id)
            await _relayed_command(base, session_id, grant, seq, within=left)
            return time.monotonic() - since
        except Exception as exc:
            tries.append(f"{time.monotonic() - since:.2f} s: {type(exc).__name__}: {exc}"[:160])
            await asyncio.sleep(0.2)
    raise AssertionError(f"no relayed answer within {ANSWER_AGAIN_S} s: {tries}")


async def test_the_relay_answers_every_vehicle_again_within_5_s_of_a_redis_restart(
    record_property: Any,
) -> None:
    cars, credentials = await db(_fleet)
    tokens = [
        await db(lambda name=name: token_issue(user=f.user(username=name), name="t"))
        for name in ("alice", "bob")
    ]
    with (
        redis_server_process() as redis,
        platform_process(extra_env={"REDIS_URL": redis.url}) as base,
    ):
        async with contextlib.AsyncExitStack() as stack:
            agents = [
                await stack.enter_async_context(car_agent(base, car, credential))
                for car, credential in zip(cars, credentials, strict=True)
            ]
            for car in cars:
                await agent_registered(car, within=30)
            tasks = [await _session_requested(base, token) for token in tokens]
            assert {t["vehicle_id"] for t in tasks} == {str(car.pk) for car in cars}
            # Each user drives their car over the relay, then leaves it.
            for task in tasks:
                await _relayed_command(base, task["session_id"], task["grant"], 1, within=10)
            uplinks = [agent.uplink for agent in agents]
            connections = [uplink.connections for uplink in uplinks if uplink is not None]
            assert len(connections) == len(agents)

            await asyncio.to_thread(
                redis.kill
            )  # it keeps nothing on disk: every group is gone with it
            await asyncio.sleep(OUTAGE_S)
            await asyncio.to_thread(redis.start)
            back = time.monotonic()

            tries: list[list[str]] = [[] for _ in tasks]
            try:
                took = await asyncio.gather(
                    *(
                        _answered_again(base, token, task["session_id"], since=back, tries=failed)
                        for token, task, failed in zip(tokens, tasks, tries, strict=True)
                    )
                )
            finally:
                record_property("failed_tries", tries)
            record_property("relay_answered_again_s", [round(t, 2) for t in took])
            # The same agents on the same uplinks: nothing was restarted or reconnected.
            assert [agent.uplink for agent in agents] == uplinks
            assert [u.connections for u in uplinks if u is not None] == connections
            for task in tasks:
                session = await db(Session.objects.get, pk=task["session_id"])
                assert session.state == Session.State.ACTIVE, session.reason
