"""Supervision that cannot be lost, on the real servers: the platform, PostgreSQL, Redis, a
Celery worker with its beat, and vehicle agents on their simulators.

Each test breaks something the way it breaks in the field (an agent killed, a user who
never comes, a stolen credential, a greedy client) and checks that the platform's word
still reaches the vehicle and the session follows what really happened.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from django.conf import settings

from accounts.roles import MONITOR
from accounts.tokens import token_issue
from fleet.credentials import vehicle_issue_credential
from fleet.models import AgentMessage, Vehicle
from services.models import Session
from services.sessions.signing import platform_public_key_pem
from tests import factories as f
from tests.control import command
from tests.servers import (
    ROOT,
    celery_worker_process,
    db,
    platform_process,
    redis_server_process,
    until,
)
from tests.vehicles import (
    api,
    car_agent,
    car_served,
    controller_present,
    drive,
    request_car,
)

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
]

CAR_COMMANDS = ["forward", "backward", "left", "right", "stop"]
#: Short timers, so the rules act within a test's patience (defaults: 30 s and 120 s).
TIMERS = {
    "IOUV_RECONNECT_GRACE_S": "4",
    "IOUV_CONNECT_TIMEOUT_S": "4",
    "IOUV_SUPERVISION_TICK_S": "0.5",
}


def _fleet(cap: int = 1) -> tuple[Vehicle, str, Any]:
    return car_served(
        "car-1", service="drive-car", commands=CAR_COMMANDS, max_sessions_per_user=cap
    )


@pytest.fixture
def servers() -> Iterator[str]:
    """The platform and a worker with its beat, on the test database and Redis."""
    with platform_process() as base, celery_worker_process(extra_env=TIMERS):
        yield base


async def _status(vehicle: Vehicle) -> str:
    return (await db(Vehicle.objects.get, pk=vehicle.pk)).status


async def _session(session_id: str) -> Session:
    return await db(Session.objects.get, pk=session_id)


async def _idle(vehicle: Vehicle) -> bool:
    return await _status(vehicle) == Vehicle.Status.IDLE


# --- an agent in a process of its own, to be killed --------------------------------------


class AgentProcess:
    """One simulated car's agent in a process of its own (``python -m agents sim fleet``
    with that car's config alone), to be killed as a vehicle's agent can be."""

    def __init__(self, config: Path) -> None:
        self.config = config
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.log = open(self.config.with_suffix(".log"), "a")  # noqa: SIM115 - closed in stop
        only = ["--configs", str(self.config.parent), "--only", self.config.stem]
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "agents", "sim", "fleet", *only],
            cwd=ROOT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
            stdout=self.log,
            stderr=subprocess.STDOUT,
        )

    def kill(self) -> None:
        """SIGKILL: no goodbye, no safe action, the socket dies with the process."""
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


@pytest.fixture
def agent_process(tmp_path: Path) -> Iterator[Any]:
    started: list[AgentProcess] = []

    def make(*, base: str, vehicle: Vehicle, credential: str, key: str) -> AgentProcess:
        config = tmp_path / f"{vehicle.name}.json"
        config.write_text(
            json.dumps(
                {
                    "platform_url": base.replace("http", "ws"),
                    "vehicle_id": str(vehicle.pk),
                    "credential": credential,
                    "platform_public_key": key,
                    "adapter": "car",
                    "adapter_options": {"origin": list(f.HOME)},
                    "control": {"host": "127.0.0.1", "port": 0},
                    "name": vehicle.name,
                }
            )
        )
        process = AgentProcess(config)
        process.start()
        started.append(process)
        return process

    yield make
    for process in started:
        process.stop()


# --- the tests ---------------------------------------------------------------------------


async def test_a_killed_agent_ends_its_session_and_its_vehicle_is_held_until_it_is_back(
    servers, agent_process, record_property
):
    base = servers
    car, credential, _service = await db(_fleet)
    key = await db(platform_public_key_pem)
    token = await db(lambda: token_issue(user=f.user(username="alice"), name="t"))
    agent = agent_process(base=base, vehicle=car, credential=credential, key=key)
    await until(lambda: _idle(car), within=30, what="the agent to register")

    body = await request_car(base, token)
    session_id = body["session"]["id"]
    driver = await drive(body["task"], 1)

    async def active() -> bool:
        return (await _session(session_id)).state == Session.State.ACTIVE

    # The driver is there when the agent dies (a loaded machine took longer than the
    # car's link-loss timeout to see the session active: its fail-safe, not the kill,
    # then ended the session).
    async with controller_present(driver):
        await until(active, what="the session to start")
        agent.kill()
        killed = time.monotonic()

    async def ended() -> Session | None:
        session = await _session(session_id)
        return session if session.state == Session.State.ENDED else None

    # The offline timeout, plus the 5 s the issue allows for the rule to act.
    session = await until(ended, within=settings.IOUV_VEHICLE_LOST_S + 5 + 10, what="the end")
    record_property("killed_to_ended_s", round(time.monotonic() - killed, 2))
    assert time.monotonic() - killed <= settings.IOUV_VEHICLE_LOST_S + 5
    lost = settings.IOUV_VEHICLE_LOST_S
    assert session.reason == f"vehicle car-1 went offline (no word from it for {lost:g} s)"
    # Nobody knows where the car is: it is not given to anyone.
    assert await _status(car) == Vehicle.Status.OFFLINE

    # Back, freshly started: it runs nothing, owes nothing, and serves the next user.
    agent_process(base=base, vehicle=car, credential=credential, key=key)
    await until(lambda: _idle(car), within=30, what="the restarted agent to register")
    pending = await db(
        lambda: list(
            AgentMessage.objects.filter(vehicle=car, state="pending").values_list("kind", flat=True)
        )
    )
    assert pending == []
    body = await request_car(base, token)
    ws = await drive(body["task"], 2)
    await ws.close()


async def test_a_session_nobody_connects_to_ends_and_its_vehicle_is_freed(servers):
    base = servers
    car, credential, _service = await db(_fleet)
    user = await db(f.user, "bob")
    async with car_agent(base, car, credential) as agent:
        await until(lambda: _idle(car), within=30, what="the agent to register")
        token = await db(lambda: token_issue(user=user, name="t"))
        body = await request_car(base, token)
        session_id = body["session"]["id"]

        async def task_arrived() -> bool:
            return agent.hub is not None and agent.hub.task is not None

        await until(task_arrived, what="the task to reach the agent")

        async def ended() -> Session | None:
            session = await _session(session_id)
            return session if session.state == Session.State.ENDED else None

        session = await until(ended, within=30, what="the unjoined session to end")
        assert session.reason == "nobody connected to the vehicle within 4 s"

        async def released() -> bool:
            return agent.hub is not None and agent.hub.task is None and await _idle(car)

        # The agent was told, confirmed, and the car is free for the next user.
        await until(released, what="the agent to end its task and the car to be free")


async def test_a_replaced_credential_cuts_the_live_uplink_within_a_second(servers, record_property):
    base = servers
    car, credential, _service = await db(_fleet)
    async with car_agent(base, car, credential) as agent:
        await until(lambda: _idle(car), within=30, what="the agent to register")
        assert agent.uplink is not None and agent.uplink.connected.is_set()
        issued = time.monotonic()
        await db(vehicle_issue_credential, vehicle=car)

        async def cut() -> bool:
            return agent.uplink is not None and not agent.uplink.connected.is_set()

        await until(cut, within=5, what="the old credential's uplink to close")
        record_property("credential_to_cut_s", round(time.monotonic() - issued, 2))
        assert time.monotonic() - issued < 1.0
        # The old holder cannot come back: the car goes offline, and any reconnection
        # it tries is refused.
        await until(lambda: _offline(car), within=10, what="the car to be offline")
        assert agent.uplink.connections == 1


async def _offline(vehicle: Vehicle) -> bool:
    return await _status(vehicle) == Vehicle.Status.OFFLINE


async def test_a_client_cannot_reserve_more_than_the_services_cap(servers):
    base = servers
    _car, _credential, _service = await db(_fleet)
    for i in range(4):  # more cars than the cap, all idle
        await db(
            f.vehicle,
            station=await db(f.station),
            vtype=await db(f.vehicle_type, "ground", "car"),
            name=f"car-extra-{i}",
            environments=["land"],
        )
    token = await db(lambda: token_issue(user=f.user(username="greedy"), name="t"))
    answers = await asyncio.gather(
        *(
            asyncio.to_thread(api, base, "POST", "/sessions", token, {"service": "drive-car"})
            for _ in range(5)
        )
    )
    statuses = sorted(status for status, _ in answers)
    assert statuses == [201, 409, 409, 409, 409], answers
    refused = [body for status, body in answers if status == 409]
    assert all(b["error"]["code"] == "session_limit" for b in refused)
    reserved = await db(lambda: Vehicle.objects.filter(status=Vehicle.Status.RESERVED).count())
    assert reserved == 1


async def test_a_monitor_stop_during_a_redis_outage_reaches_the_vehicle(record_property):
    """Redis dies while a user drives; a monitor stops the session. The stop is owed in
    the database, so it reaches the car at once, Redis or not; the user drives no more,
    and once Redis is back the car serves the next session."""
    car, credential, _service = await db(_fleet)
    alice = await db(lambda: token_issue(user=f.user(username="alice"), name="t"))
    mona = await db(lambda: token_issue(user=f.user(username="mona", roles=(MONITOR,)), name="t"))
    with (
        redis_server_process() as redis,
        platform_process(extra_env={"REDIS_URL": redis.url}) as base,
    ):
        async with car_agent(base, car, credential) as agent:
            await until(lambda: _idle(car), within=30, what="the agent to register")
            body = await request_car(base, alice)
            session_id = body["session"]["id"]
            ws = await drive(body["task"], 1)

            acked_at: list[float] = []

            async def keep_driving() -> None:
                seq = 10
                with contextlib.suppress(Exception):  # ends when the agent drops us
                    while True:
                        seq += 1
                        if (await command(ws, seq, "forward", speed=0.5))["ok"]:
                            acked_at.append(time.monotonic())
                        await asyncio.sleep(0.1)

            driving = asyncio.create_task(keep_driving())
            await until(lambda: _true(len(acked_at) >= 3), what="the user to drive")

            await asyncio.to_thread(redis.kill)
            status, body = await asyncio.to_thread(
                api, base, "POST", f"/sessions/{session_id}/stop", mona
            )
            stopped = time.monotonic()
            assert status == 200 and body["state"] == "aborted", body

            async def car_stopped() -> bool:
                return agent.hub is not None and agent.hub.task is None

            await until(car_stopped, within=10, what="the revoke to reach the car")
            record_property("stop_answered_to_car_stopped_s", round(time.monotonic() - stopped, 2))
            assert time.monotonic() - stopped < 2.0
            assert agent.adapter.telemetry()["motors"] == {"left": 0.0, "right": 0.0}
            await asyncio.wait_for(driving, 10)
            assert not [t for t in acked_at if t > stopped + 0.5], "the user kept driving"

            async def stop_confirmed() -> bool:
                _, session = await asyncio.to_thread(
                    api, base, "GET", f"/sessions/{session_id}", mona
                )
                return [d["state"] for d in session["delivery"]] == ["delivered"]

            await until(stop_confirmed, within=10, what="the stop to be confirmed")

            await asyncio.to_thread(redis.start)
            await until(lambda: _idle(car), within=10, what="the car to be free")
            body = await request_car(base, alice)
            ws = await drive(body["task"], 100)
            await ws.close()


async def _true(value: bool) -> bool:
    return value


async def test_a_driver_whose_keepalives_stall_for_a_second_keeps_the_session(servers):
    """A throttled tab: nothing from the driver for 1 s, so the car's watchdog stops it;
    then the driver goes on on the same socket. The session must go on too, past the
    reconnection grace (4 s here), instead of ending as an unintentional end."""
    base = servers
    car, credential, _service = await db(_fleet)
    alice = await db(lambda: token_issue(user=f.user(username="alice"), name="t"))
    async with car_agent(base, car, credential) as agent:
        await until(lambda: _idle(car), within=30, what="the agent to register")
        body = await request_car(base, alice)
        session_id = body["session"]["id"]
        ws = await drive(body["task"], 1)

        # The stall itself (a tab the browser throttled): at least 1 s, and until the
        # car's watchdog has acted on it.
        await asyncio.sleep(1.0)

        async def failsafe_fired() -> bool:
            return agent.hub is not None and agent.hub.stats["failsafes"] == 1

        await until(failsafe_fired, what="the watchdog to stop the car")

        async def logged(kind: str) -> bool:
            return await db(
                lambda: Session.objects.get(pk=session_id).events.filter(kind=kind).exists()
            )

        await until(lambda: logged("unintentional_end"), what="the fail-safe to be logged")
        # The driver drives on, on the same socket, for longer than the grace.
        # Checked while it drives: once it stops, the watchdog stops the car again.
        seq = 10
        started = time.monotonic()
        while True:
            seq += 1
            assert (await command(ws, seq, "forward", speed=0.3))["ok"]
            if (
                time.monotonic() - started >= 4 + 3
                and await logged("link_recovered")
                and await _status(car) == Vehicle.Status.IN_SERVICE
            ):
                break
            assert time.monotonic() - started < 60, "the car was not back in service"
            await asyncio.sleep(0.1)
        session = await _session(session_id)
        assert session.state == Session.State.ACTIVE, session.reason
        await ws.close()
