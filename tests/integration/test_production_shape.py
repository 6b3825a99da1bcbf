"""The production shape, run from deploy/'s own files (tests.production): nginx with TLS
in front, two gunicorn HTTP processes, two uvicorn WebSocket processes, the Celery
worker with its beat, PostgreSQL and Redis; two cars whose agents dial in through nginx.

A deploy restarts every process one at a time while one user drives point-to-point (on
the car's own socket, as over WebRTC), another over the platform's relay, and a program
reads the API: no session ends, no direct command is lost, the relayed user drives
again within 5 s of each restart that cut them off, and the API never fails.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import ssl
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection, connect

from accounts.tokens import token_issue
from fleet.credentials import vehicle_issue_credential
from fleet.models import Vehicle
from services.models import Session
from tests import factories as f
from tests.control import command, recv
from tests.production import ProductionShape
from tests.servers import agent_running, db, until
from tests.vehicles import car_served

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.realtime,
    pytest.mark.django_db(transaction=True),
]

#: The supervisor's timers, short: every restart lasts longer than the offline and
#: lost-vehicle timeouts. A relayed user cut off by a restart has the grace to come back.
TIMERS = {
    "IOUV_OFFLINE_AFTER_S": "2",
    "IOUV_VEHICLE_LOST_S": "2",
    "IOUV_RECONNECT_GRACE_S": "10",
    "IOUV_SUPERVISION_TICK_S": "0.5",
}


def _fleet() -> tuple[list[Vehicle], list[str]]:
    """Two cars at one station, both matching the drive-car service."""
    car, credential, _service = car_served("car-1", service="drive-car")
    other = f.vehicle(
        station=car.station,
        vtype=car.vehicle_type,
        name="car-2",
        online=False,
        **car.attributes,
    )
    return [car, other], [credential, vehicle_issue_credential(vehicle=other)]


def _api(base: str, context: ssl.SSLContext, method: str, path: str, token: str) -> tuple[int, Any]:
    request = urllib.request.Request(
        f"{base}/api/v1{path}",
        method=method,
        data=json.dumps({"service": "drive-car"}).encode() if method == "POST" else None,
        headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
    )
    try:
        with urllib.request.urlopen(request, timeout=20, context=context) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


class Reader:
    """A program reading the API through nginx every 100 ms, counting failures."""

    def __init__(self, shape: ProductionShape, token: str) -> None:
        self.failures: list[Any] = []
        self.answered = 0
        self._task = asyncio.create_task(self._read(shape, token))

    async def _read(self, shape: ProductionShape, token: str) -> None:
        while True:
            try:
                status, body = await asyncio.to_thread(
                    _api, shape.base, shape.context, "GET", "/services", token
                )
            except OSError as exc:
                status, body = 0, str(exc)
            if status == 200:
                self.answered += 1
            else:
                self.failures.append((status, body))
            await asyncio.sleep(0.1)

    async def stop(self) -> None:
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task


class Driver:
    """A user holding ``forward``, a command every 100 ms. ``direct``: on the car's
    own socket (the platform is not on that path); else over the relay, reconnecting
    with a fresh grant whenever the socket closes, as the controller page does."""

    def __init__(
        self, shape: ProductionShape, token: str, task: dict[str, Any], *, direct: bool
    ) -> None:
        self.shape, self.token, self.task, self.direct = shape, token, task, direct
        self.sent = self.acked = 0
        #: The last answer that refused a fresh grant (a failure says it).
        self.refused: Any = None
        #: What happened to the connection, with when (monotonic): a failure says it.
        self.log: list[tuple[float, str]] = []
        self.acked_at: list[float] = []
        self.ws: ClientConnection | None = None
        self._runner = asyncio.create_task(self._run())

    async def _connect(self) -> ClientConnection:
        if self.direct:
            ws = await connect(self.task["control_url"], proxy=None, compression=None)
        else:
            url = f"wss://127.0.0.1:{self.shape.https}/ws/relay/{self.task['session_id']}/"
            ws = await connect(url, ssl=self.shape.context, proxy=None, compression=None)
        await ws.send(json.dumps({"type": "auth", "grant": self.task["grant"]}))
        # The vehicle may still count the socket the restart cut as its controller:
        # gone silent, it hands the controls to the user's new connection.
        assert (await recv(ws, "welcome", within=10))["role"] == "controller"
        return ws

    async def _run(self) -> None:
        seq = 0
        while True:
            try:
                self.ws = await self._connect()
                while True:
                    seq += 1
                    self.sent += 1
                    if (await command(self.ws, seq, "forward", speed=0.3))["ok"]:
                        self.acked += 1
                        self.acked_at.append(time.monotonic())
                    await asyncio.sleep(0.1)
            except Exception as exc:
                if self.direct:
                    raise  # the car's own socket never goes through the platform
                self.log.append((time.monotonic(), f"{type(exc).__name__}: {exc}"[:120]))
                # The relay's process restarted: a fresh grant, and on again.
                await asyncio.sleep(0.2)
                status, body = await asyncio.to_thread(
                    _api,
                    self.shape.base,
                    self.shape.context,
                    "POST",
                    f"/sessions/{self.task['session_id']}/grant",
                    self.token,
                )
                if status == 200:
                    self.task = body["task"]
                else:
                    self.refused = (status, body)

    def longest_gap(self, since: float) -> float:
        """The longest time without an acknowledged command since ``since``."""
        times = [since, *(t for t in self.acked_at if t > since), time.monotonic()]
        return max(b - a for a, b in itertools.pairwise(times))

    async def until_acked(self, more: int) -> None:
        target = self.acked + more

        async def done() -> bool:
            if self._runner.done():
                self._runner.result()
            return self.acked >= target

        what = f"{more} more commands acknowledged (last grant refusal: {self.refused})"
        await until(done, within=30, what=what)

    async def stop(self) -> None:
        self._runner.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._runner
        if self.ws is not None:
            await self.ws.close()


async def test_a_rolling_restart_of_every_process_ends_no_session(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    shape = ProductionShape(tmp_path, env=TIMERS)
    # The agents' uplinks (in this process) trust the test's CA, as a vehicle trusts
    # the platform's certificate.
    monkeypatch.setenv("SSL_CERT_FILE", str(shape.certificates.ca))
    cars, credentials = await db(_fleet)
    alice = await db(lambda: token_issue(user=f.user(username="alice"), name="t"))
    bob = await db(lambda: token_issue(user=f.user(username="bob"), name="t"))
    with shape.running():
        async with contextlib.AsyncExitStack() as stack:
            for car, credential in zip(cars, credentials, strict=True):
                await stack.enter_async_context(
                    agent_running(
                        base=shape.base,
                        vehicle=car,
                        credential=credential,
                        adapter="car",
                        options={"origin": list(f.HOME)},
                    )
                )

            async def both_idle() -> bool:
                statuses = await db(lambda: set(Vehicle.objects.values_list("status", flat=True)))
                return statuses == {Vehicle.Status.IDLE}

            await until(both_idle, within=30, what="both agents registered through nginx")

            seen: list[Any] = []

            async def both_in_service() -> bool:
                seen[:] = await db(lambda: sorted(Vehicle.objects.values_list("name", "status")))
                return {status for _, status in seen} == {Vehicle.Status.IN_SERVICE}

            sessions = []
            drivers = []
            for token, direct in ((alice, True), (bob, False)):
                status, body = await asyncio.to_thread(
                    _api, shape.base, shape.context, "POST", "/sessions", token
                )
                assert status == 201, body
                sessions.append(body["session"]["id"])
                await _task_accepted(body["session"]["id"])
                drivers.append(Driver(shape, token, body["task"], direct=direct))
            direct_driver, relayed = drivers
            reader = Reader(shape, alice)
            try:
                for driver in drivers:
                    await driver.until_acked(5)

                # The deploy: each HTTP process, then each WebSocket process, then the
                # worker (with its beat), one at a time.
                for process in shape.web:
                    await asyncio.to_thread(process.restart)
                    await direct_driver.until_acked(3)
                for process in shape.ws:
                    restarted = time.monotonic()
                    await asyncio.to_thread(process.restart)
                    await relayed.until_acked(5)
                    gap = relayed.longest_gap(restarted)
                    happened = [(round(t - restarted, 2), what) for t, what in relayed.log]
                    assert gap <= 5.0, f"relayed driving stopped for {gap:.1f} s: {happened}"
                    # As a deploy does: the next one once the agents are back.
                    try:
                        await until(both_in_service, within=30, what="both agents back")
                    except AssertionError:
                        raise AssertionError(f"the agents are not back: {seen}") from None
                await asyncio.to_thread(shape.worker.stop)
                await asyncio.to_thread(shape.worker.start)

                # Past every timer with everything back.
                back = time.monotonic()
                while time.monotonic() - back < 6.0:
                    await direct_driver.until_acked(1)
                for session_id in sessions:
                    session = await db(Session.objects.get, pk=session_id)
                    assert session.state == Session.State.ACTIVE, session.reason
                assert direct_driver.sent - direct_driver.acked <= 1
                assert reader.answered > 0 and reader.failures == [], reader.failures[:5]
            finally:
                await reader.stop()
                for driver in drivers:
                    await driver.stop()


async def _task_accepted(session_id: str) -> None:
    async def accepted() -> bool:
        return await db(
            lambda: Session.objects.get(pk=session_id).events.filter(kind="task_accepted").exists()
        )

    await until(accepted, within=15, what="the agent to accept its task")
