"""Users and programs on the production shape (tests.production): the cars they ask
for, a program reading the API through nginx, a user driving on the car's own socket or
over the platform's relay, counting what was acknowledged and when."""

from __future__ import annotations

import asyncio
import collections
import http.client
import itertools
import json
import ssl
import time
import urllib.error
import urllib.request
from typing import Any

from websockets.asyncio.client import ClientConnection, connect

from fleet.credentials import vehicle_issue_credential
from fleet.models import Vehicle
from services.models import Session
from tests import factories as f
from tests.control import recv
from tests.production import ProductionShape
from tests.servers import cancelled, db, until
from tests.vehicles import car_served


def car_fleet(count: int = 2) -> tuple[list[Vehicle], list[str]]:
    """``count`` cars (car-1, car-2...) at one station, all matching the drive-car
    service; their credentials."""
    car, credential, _service = car_served("car-1", service="drive-car")
    cars, credentials = [car], [credential]
    for number in range(2, count + 1):
        other = f.vehicle(
            station=car.station,
            vtype=car.vehicle_type,
            name=f"car-{number}",
            online=False,
            **car.attributes,
        )
        cars.append(other)
        credentials.append(vehicle_issue_credential(vehicle=other))
    return cars, credentials


def api(base: str, context: ssl.SSLContext, method: str, path: str, token: str) -> tuple[int, Any]:
    """One API request through nginx (a POST asks for the drive-car service): its status
    and its JSON body (the raw body of an error)."""
    request = urllib.request.Request(
        f"{base}/api/v1{path}",
        method=method,
        data=json.dumps({"service": "drive-car"}).encode() if method == "POST" else None,
        headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
    )
    try:
        # Patient enough for a GET nginx passes on after proxy_read_timeout (15 s).
        with urllib.request.urlopen(request, timeout=30, context=context) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


class Reader:
    """A program reading the API through nginx every 100 ms, counting failures, and
    timing the answers: ``answered_at`` holds (when it was asked, seconds it took)."""

    def __init__(self, shape: ProductionShape, token: str) -> None:
        self.failures: list[Any] = []
        self.answered = 0
        self.answered_at: list[tuple[float, float]] = []
        self._task = asyncio.create_task(self._read(shape, token))

    async def _read(self, shape: ProductionShape, token: str) -> None:
        while True:
            asked = time.monotonic()
            try:
                status, body = await asyncio.to_thread(
                    api, shape.base, shape.context, "GET", "/services", token
                )
            except (OSError, http.client.HTTPException) as exc:  # refused, reset, cut short
                status, body = 0, repr(exc)
            if status == 200:
                self.answered += 1
                self.answered_at.append((asked, time.monotonic() - asked))
            else:
                self.failures.append((status, body))
            await asyncio.sleep(0.1)

    async def stop(self) -> None:
        await cancelled(self._task)


class Driver:
    """A user holding ``forward``, a command every 100 ms once the last is answered.
    ``direct``: on the car's own socket (the platform is not on that path); else over
    the relay, as the controller page does: a command unanswered for 3 s is forgotten
    and the next sent, and a closed socket connects again with a fresh grant, as does a
    path gone silent: two commands unanswered in a row here, 6 s (the page gives a
    socket up after 5 s without a word)."""

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
        #: How many commands the vehicle refused, by code (a failure says it).
        self.refusals: collections.Counter[str] = collections.Counter()
        self.ws: ClientConnection | None = None
        self._closing: set[asyncio.Task[None]] = set()
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
                silent = 0  # commands in a row the vehicle did not answer
                while True:
                    seq += 1
                    self.sent += 1
                    command = {"type": "command", "seq": seq, "name": "forward"}
                    await self.ws.send(json.dumps({**command, "args": {"speed": 0.3}}))
                    try:
                        ack = await self._ack(seq)
                    except TimeoutError:
                        if self.direct:
                            raise
                        # As the controller page does, a command unanswered for 3 s is
                        # forgotten and the next goes on the same socket: the vehicle's
                        # uplink moving to another process loses one. Two in a row is a
                        # path gone silent (a machine cut off): connect again.
                        silent += 1
                        self.log.append((time.monotonic(), f"no answer to command {seq}"))
                        if silent >= 2:
                            raise
                        continue
                    silent = 0
                    if ack["ok"]:
                        self.acked += 1
                        self.acked_at.append(time.monotonic())
                    else:
                        self.refusals[str(ack.get("code"))] += 1
                    await asyncio.sleep(0.1)
            except Exception as exc:
                if self.direct:
                    raise  # the car's own socket never goes through the platform
                self.log.append((time.monotonic(), f"{type(exc).__name__}: {exc}"[:120]))
                if self.ws is not None:
                    # A silent one too (nginx would keep it open), without waiting on
                    # a goodbye a machine cut off never sends.
                    self._closing.add(asyncio.create_task(self.ws.close()))
                    self.ws = None
                # The relay's process restarted: a fresh grant, and on again.
                await asyncio.sleep(0.2)
                status, body = await asyncio.to_thread(
                    api,
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

    async def _ack(self, seq: int) -> dict[str, Any]:
        """The answer to command ``seq``, past the late answers to the ones forgotten.

        Late is not lost on the car's own socket: a saturated machine's answer took
        longer than the usual 3 s (20 s allowed). Over the relay, 3 s, as the page."""
        assert self.ws is not None
        deadline = time.monotonic() + (20 if self.direct else 3)
        while True:
            ack = await recv(self.ws, "ack", within=max(0.0, deadline - time.monotonic()))
            if ack.get("seq") == seq:
                return ack

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

        try:
            await until(done, within=30, what=f"{more} more commands acknowledged")
        except AssertionError as exc:
            raise AssertionError(
                f"{exc} (refused by the vehicle: {dict(self.refusals)}; "
                f"last grant refusal: {self.refused})"
            ) from None

    async def stop(self) -> None:
        await cancelled(self._runner)
        for closing in self._closing:
            await cancelled(closing)
        if self.ws is not None:
            await self.ws.close()


async def task_accepted(session_id: str) -> None:
    """Wait until the agent accepted the session's task."""

    async def accepted() -> bool:
        return await db(
            lambda: Session.objects.get(pk=session_id).events.filter(kind="task_accepted").exists()
        )

    await until(accepted, within=15, what="the agent to accept its task")
