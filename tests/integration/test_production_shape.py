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
import time
from pathlib import Path
from typing import Any

import pytest

from accounts.tokens import token_issue
from fleet.models import Vehicle
from services.models import Session
from tests import factories as f
from tests.production import ProductionShape
from tests.production_clients import Driver, Reader, api, car_fleet, task_accepted
from tests.servers import agent_running, db, until

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


async def test_a_rolling_restart_of_every_process_ends_no_session(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    shape = ProductionShape(tmp_path, env=TIMERS)
    # The agents' uplinks (in this process) trust the test's CA, as a vehicle trusts
    # the platform's certificate.
    monkeypatch.setenv("SSL_CERT_FILE", str(shape.certificates.ca))
    cars, credentials = await db(car_fleet)
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
                    api, shape.base, shape.context, "POST", "/sessions", token
                )
                assert status == 201, body
                sessions.append(body["session"]["id"])
                await task_accepted(body["session"]["id"])
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
