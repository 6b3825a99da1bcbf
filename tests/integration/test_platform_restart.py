"""A platform gap is not a vehicle gap: the platform process is killed, or stopped and
started again as a deploy does, while a user drives a car point-to-point; the car's
agent reconnects when the platform is back and the session goes on.

Real servers throughout: the platform under its server, PostgreSQL, Redis, a Celery
worker with its beat running the supervision timers (short here), and the car's agent
on its simulator. The worker keeps running while the platform is away, as it does in
production, so its timers see every vehicle go silent at once.
"""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any

import pytest

from accounts.tokens import token_issue
from fleet.models import Vehicle
from services.models import Session
from tests import factories as f
from tests.control import recv
from tests.servers import cancelled, celery_worker_process, db, platform_server, until
from tests.vehicles import car_agent, car_served, drive, request_car

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.realtime,
    pytest.mark.django_db(transaction=True),
]

#: Timers short enough that a gap of OUTAGE_S is, for each of them, far past due: a
#: vehicle silent 2 s is offline, offline 2 s more is lost; a user gone 3 s is gone.
TIMERS = {
    "IOUV_OFFLINE_AFTER_S": "2",
    # Four heartbeats in that time, as production has three (2 s in 6 s): a live
    # agent on a loaded machine is never a heartbeat away from being called silent.
    "IOUV_HEARTBEAT_INTERVAL_S": "0.5",
    "IOUV_VEHICLE_LOST_S": "2",
    "IOUV_RECONNECT_GRACE_S": "3",
    "IOUV_SUPERVISION_TICK_S": "0.5",
}
#: How long the platform stays away when it is killed: every timer above, twice over.
OUTAGE_S = 8.0


class Driver:
    """A user holding the car's controls, a command every 100 ms on the car's own
    socket, counting the acknowledgements (the platform is not on that path)."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.sent = 0
        self.acked = 0
        self._task = asyncio.create_task(self._drive())

    async def _drive(self) -> None:
        seq = 100
        while True:
            seq += 1
            self.sent += 1
            command = {"type": "command", "seq": seq, "name": "forward", "args": {"speed": 0.3}}
            await self.ws.send(json.dumps(command))
            # Late is not lost: on a machine saturated while the platform starts up
            # again, an answer may take longer than the usual 3 s.
            if (await recv(self.ws, "ack", within=20))["ok"]:
                self.acked += 1
            await asyncio.sleep(0.1)

    async def until_acked(self, more: int) -> None:
        """Wait for ``more`` acknowledged commands than now."""
        target = self.acked + more

        async def done() -> bool:
            if self._task.done():
                self._task.result()  # raise what stopped the driving
            return self.acked >= target

        await until(done, within=30, what=f"{more} more commands acknowledged")

    async def stop(self) -> None:
        await cancelled(self._task)
        await self.ws.close()


async def _state(session_id: str) -> tuple[str, str]:
    session = await db(Session.objects.get, pk=session_id)
    return session.state, session.reason


async def _serving(car: Vehicle) -> bool:
    """The car's agent is back on an uplink and holds its session's status."""
    status = (await db(Vehicle.objects.get, pk=car.pk)).status
    return status == Vehicle.Status.IN_SERVICE


@pytest.mark.parametrize("how", ["kill", "restart"])
async def test_a_driven_session_outlives_the_platform_going_away(how: str) -> None:
    car, credential, _service = await db(lambda: car_served("car-1", service="drive-car"))
    alice = await db(lambda: token_issue(user=f.user(username="alice"), name="t"))
    with (
        platform_server(extra_env=TIMERS) as platform,
        celery_worker_process(extra_env=TIMERS),
    ):
        async with car_agent(platform.base, car, credential):
            await until(lambda: _idle(car), within=30, what="the agent to register")
            body = await request_car(platform.base, alice)
            session_id = body["session"]["id"]
            driver = Driver(await drive(body["task"], 1))
            try:
                await driver.until_acked(5)
                # The platform marks the car in service once it hears the task taken:
                # on a busy machine that may come after the first commands.
                await until(lambda: _serving(car), within=30, what="the car in service")

                if how == "kill":
                    # Off the event loop: the agent and the driver share it, and a
                    # test that blocks it makes a link loss of its own.
                    await asyncio.to_thread(platform.kill)  # a crash: no goodbye at all
                    # Driving goes on point-to-point while the supervisor's timers
                    # run on the car's silence, for twice as long as any of them.
                    gone_at = time.monotonic()
                    await driver.until_acked(int(OUTAGE_S * 5))
                    while time.monotonic() - gone_at < OUTAGE_S:
                        await driver.until_acked(1)
                else:
                    # a deploy: SIGTERM, then at once...
                    await asyncio.to_thread(platform.terminate)
                # ...the platform is back on the same address
                await asyncio.to_thread(platform.start)

                await until(lambda: _serving(car), within=45, what="the car back in service")
                # Past every timer again, with the platform up.
                back_at = time.monotonic()
                while time.monotonic() - back_at < 6.0:
                    await driver.until_acked(1)
                state, reason = await _state(session_id)
                assert state == Session.State.ACTIVE, reason
                assert driver.acked == driver.sent or driver.sent - driver.acked <= 1
            finally:
                await driver.stop()


async def _idle(vehicle: Vehicle) -> bool:
    return (await db(Vehicle.objects.get, pk=vehicle.pk)).status == Vehicle.Status.IDLE
