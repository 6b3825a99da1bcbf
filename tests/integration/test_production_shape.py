"""The production shape, run from deploy/'s own files (tests.production): nginx with TLS
in front, two gunicorn HTTP processes, two uvicorn WebSocket processes, the Celery
worker with its beat, PostgreSQL and Redis; the demo's four cars and its sea rescue
fleet, whose agents dial in through nginx.

Every platform process, one at a time, is restarted as a deploy restarts it, then, one
at a time again, killed and brought back as systemd brings back a crashed unit, while
three users drive over WebRTC, a fourth over the platform's relay, a rescue at sea runs
and a program reads the API: no session ends, no WebRTC command is lost, the relayed
user drives again within 5 s of each restart or kill that cut them off, the API never
fails across the restarts (across the kills, only the answers a killed process was
sending), and the rescue completes, once. Both rounds run on one platform and fleet:
setting them up is most of the cost of this test.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import time
from pathlib import Path
from typing import Any

import pytest

from accounts.tokens import token_issue
from agents.config import AgentConfig
from benchmarks.rtc_client import RtcClientError, RtcControlClient
from fleet.models import Vehicle
from kinds.rescue_at_sea.models import Mission
from kinds.rescue_at_sea.tests.sea import client_requests_rescue, search_area
from services.demo import demo_seed
from services.models import Session
from tests import factories as f
from tests.demo import PASSWORD, agents_online, mission_agent_config
from tests.production import ProductionShape
from tests.production_clients import Driver, Reader, api, task_accepted
from tests.servers import cancelled, db, until

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
    # Four heartbeats in that time, as production has three (2 s in 6 s): a live
    # agent on a loaded machine is never a heartbeat away from being called silent.
    "IOUV_HEARTBEAT_INTERVAL_S": "0.5",
    "IOUV_VEHICLE_LOST_S": "2",
    "IOUV_RECONNECT_GRACE_S": "10",
    "IOUV_SUPERVISION_TICK_S": "0.5",
}
#: The rescue's steps every second; a task a killed worker held goes to the next
#: after 5 s; e-mail to files (EMAIL_FILE_PATH, per test).
MISSIONS = {
    "IOUV_MISSION_TICK_S": "1",
    "CELERY_VISIBILITY_TIMEOUT_S": "5",
    "EMAIL_BACKEND": "django.core.mail.backends.filebased.EmailBackend",
}


class RtcDriver:
    """A user driving over WebRTC, as the controller page does: authenticated on the
    relay through nginx, then on the vehicle's data channels, a command every 100 ms.
    The platform is not on that path: a restart may take the relay socket, never the
    driving, and every command must be acknowledged."""

    def __init__(self, shape: ProductionShape, task: dict[str, Any]) -> None:
        url = f"wss://127.0.0.1:{shape.https}/ws/relay/{task['session_id']}/"
        # Late is not lost: on a saturated machine an answer may take a while.
        self.user = RtcControlClient(url, task["grant"], ice_host_addresses=["127.0.0.1"],
                                     timeout_s=20)  # fmt: skip
        self.sent = self.acked = self.answered = 0
        #: Commands the vehicle answered with a refusal: (seq, code, error).
        self.refusals: list[tuple[int, Any, Any]] = []
        self._runner: asyncio.Task[None] | None = None
        self._keepalive: asyncio.Task[None] | None = None

    async def start(self) -> None:
        await self.user.start()
        assert self.user.welcome["role"] == "controller"
        assert await self.user.path_is("webrtc_direct") == "webrtc_direct"
        self._runner = asyncio.create_task(self._run())
        self._keepalive = asyncio.create_task(self._keep_alive())

    async def _keep_alive(self) -> None:
        # As the controller page does, whatever the commands' answers are doing: the
        # agent's link-loss watchdog (500 ms here) hears the user between commands.
        while True:
            self.user.send({"type": "keepalive"})
            await asyncio.sleep(0.1)

    async def _run(self) -> None:
        for seq in itertools.count(1):
            self.sent += 1
            try:
                ack = await self.user.command(seq, "forward", speed=0.3)
            except RtcClientError as exc:
                raise RtcClientError(f"command {seq}: {exc} ({self._connection()})") from None
            self.answered += 1
            if ack["ok"]:
                self.acked += 1
            else:
                self.refusals.append((seq, ack.get("code"), ack.get("error")))
            await asyncio.sleep(0.1)

    def _connection(self) -> str:
        """The state of the user's side of the connection, for a failure to say."""
        pc = self.user.pc
        if pc is None:
            return "no peer connection"
        sctp = pc.sctp
        return (
            f"connection {pc.connectionState}, ICE {pc.iceConnectionState}, "
            f"SCTP {getattr(sctp, 'state', None)}, path {self.user.ice_path}, "
            f"{self.answered} of {self.sent} commands answered"
        )

    async def until_acked(self, more: int) -> None:
        target = self.acked + more

        async def done() -> bool:
            self.check()
            return self.acked >= target

        await until(done, within=30, what=f"{more} more commands acknowledged over WebRTC")

    def check(self) -> None:
        """Raise what stopped the driving, if something did."""
        for task in (self._runner, self._keepalive):
            if task is not None and task.done():
                task.result()

    async def stop(self) -> None:
        """Stop driving (what stopped it earlier is :meth:`check`'s to say)."""
        for task in (self._runner, self._keepalive):
            await cancelled(task)
        await self.user.close()


def _world(directory: Path, platform_url: str) -> dict[str, str]:
    """The demo world (its agents' configs in ``directory``, dialling ``platform_url``)
    and four more clients; their API tokens by name."""
    demo_seed(password=PASSWORD, credentials_dir=directory, platform_url=platform_url)
    return {
        name: token_issue(user=f.user(username=name), name="t")
        for name in ("ana", "bea", "carl", "dora")
    }


def _rescue_kinds(session_id: Any) -> list[str]:
    return list(
        Session.objects.get(pk=session_id).events.order_by("seq").values_list("kind", flat=True)
    )


def _rescue_completions(session_id: Any) -> int:
    return (
        Session.objects.get(pk=session_id)
        .events.filter(kind="mission_state", data__to=Mission.State.COMPLETED)
        .count()
    )


@pytest.mark.cost(130)
async def test_every_platform_process_restarted_then_killed_in_turn_ends_no_session(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Three users drive cars over WebRTC, a fourth over the relay, a rescue at sea runs
    by itself, and a program reads the API; each platform process in turn is restarted
    as a deploy does (SIGTERM, then started), then each in turn killed and brought back
    as systemd brings back a crashed unit (SIGKILL of its process group)."""
    shape = ProductionShape(
        tmp_path, env={**TIMERS, **MISSIONS, "EMAIL_FILE_PATH": str(tmp_path / "mail")}
    )
    # The agents' uplinks and the users (in this process) trust the test's CA, as a
    # vehicle and a browser trust the platform's certificate.
    monkeypatch.setenv("SSL_CERT_FILE", str(shape.certificates.ca))
    configs_dir = tmp_path / "agents"
    uplink = shape.base.replace("https://", "wss://")
    tokens = await db(_world, configs_dir, uplink)
    cars = ("car-1", "car-2", "car-3", "car-4")
    # The cars offer loopback alone, as the users do: an address another test adds for
    # a while (tests.netlab's bridges) must not carry a pair that vanishes with it.
    configs = {
        name: dataclasses.replace(
            AgentConfig.load(configs_dir / f"{name}.json"),
            video=None,
            webrtc={"ice_host_addresses": ["127.0.0.1"]},
            reconnect_min_s=0.2,
        )
        for name in cars
    }
    for name in ("search-1", "lifeguard-1"):
        configs[name] = mission_agent_config(configs_dir / f"{name}.json", uplink)
    with shape.running():
        async with agents_online(configs, within=60, positioned=False, what="the fleet online"):
            sessions: list[str] = []
            rtc: list[RtcDriver] = []
            relayed: Driver | None = None
            reader = Reader(shape, tokens["ana"])
            try:
                for name in ("ana", "bea", "carl", "dora"):
                    status, body = await asyncio.to_thread(
                        api, shape.base, shape.context, "POST", "/sessions", tokens[name]
                    )
                    assert status == 201, body
                    sessions.append(body["session"]["id"])
                    await task_accepted(body["session"]["id"])
                    if name == "dora":
                        relayed = Driver(shape, tokens[name], body["task"], direct=False)
                    else:
                        rtc.append(RtcDriver(shape, body["task"]))
                        await rtc[-1].start()
                assert relayed is not None
                for driver in [*rtc, relayed]:
                    await driver.until_acked(5)
                rescue = await db(client_requests_rescue, search_area())

                async def searching() -> bool:
                    return "task_accepted" in await db(_rescue_kinds, rescue.pk)

                await until(searching, within=60, what="the search drone under way")

                for how in ("restart", "kill"):
                    await _round(shape, how, rtc, relayed, configs)
                    # Past every timer with everything back.
                    back = time.monotonic()
                    while time.monotonic() - back < 6.0:
                        for driver in rtc:
                            await driver.until_acked(1)
                    for session_id in sessions:
                        session = await db(Session.objects.get, pk=session_id)
                        assert session.state == Session.State.ACTIVE, (how, session.reason)
                    if how == "restart":
                        # A deploy's restarts cost the API nothing: the answers asked
                        # for before the last one are all in by now.
                        assert reader.answered > 0, reader.failures[:5]
                        assert reader.failures == [], reader.failures[:5]
                for driver in rtc:
                    driver.check()
                    # Every command reached the vehicle and was answered (the one in
                    # flight now aside); a refusal is an answer (one that came too late
                    # on a saturated machine is refused as stale), but never because
                    # the user lost the controls.
                    assert driver.sent - driver.answered <= 1, (driver.sent, driver.answered)
                    assert all(code != "view_only" for _, code, _ in driver.refusals), (
                        driver.refusals
                    )
                # Over the relay, a restart slows the round trip past the service's
                # limit for a moment: the car refuses to move then ("latency"), and the
                # user keeps the controls and the session.
                assert "view_only" not in relayed.refusals, relayed.refusals
                # The answer a killed process was sending is cut short (nothing can
                # finish it); nginx sends every later request to a process alive.
                assert len(reader.failures) <= len(shape.web), reader.failures
                assert all(status in (0, 502) for status, _ in reader.failures)

                # The rescue, its steps run by workers that came and went, ends once.
                async def completed() -> bool:
                    return await db(_rescue_completions, rescue.pk) >= 1

                try:
                    await until(completed, within=180, what="the rescue completed")
                except AssertionError:
                    mission = await db(Mission.objects.get, pk=rescue.pk)
                    kinds = await db(_rescue_kinds, rescue.pk)
                    raise AssertionError(f"rescue {mission.state}: {kinds}") from None
                kinds = await db(_rescue_kinds, rescue.pk)
                assert kinds.count("person_detected") == 1, kinds
                assert kinds.count("payload_released") == 1, kinds
                assert await db(_rescue_completions, rescue.pk) == 1, kinds
                for driver in rtc:
                    driver.check()  # they drove all along
            finally:
                await reader.stop()
                for driver in [*rtc, *([relayed] if relayed else [])]:
                    await driver.stop()


async def _round(
    shape: ProductionShape,
    how: str,
    rtc: list[RtcDriver],
    relayed: Driver,
    configs: dict[str, AgentConfig],
) -> None:
    """The deploy (``restart``) or the crashes (``kill``): each HTTP process, then each
    WebSocket process, then the worker (with its beat), one at a time, each once the
    last is back and the users drive again."""

    def again(process: Any) -> None:
        process.restart() if how == "restart" else process.crash()

    for process in shape.web:
        await asyncio.to_thread(again, process)
        for driver in rtc:
            await driver.until_acked(3)
    for process in shape.ws:
        cut = time.monotonic()
        await asyncio.to_thread(again, process)
        await relayed.until_acked(5)
        gap = relayed.longest_gap(cut)
        happened = [(round(t - cut, 2), what) for t, what in relayed.log if t >= cut]
        # The vehicle's refusals so far, by code, say whether commands were answered
        # "no" (a round trip over the service's limit) or not at all.
        assert gap <= 5.0, (
            f"{how}: relayed driving stopped for {gap:.1f} s: {happened}; "
            f"refused so far: {dict(relayed.refusals)}"
        )
        await until(lambda: _all_back(configs), within=30, what="every agent back on an uplink")
    if how == "restart":
        await asyncio.to_thread(shape.worker.stop)
    else:
        await asyncio.to_thread(shape.worker.kill)
    await asyncio.to_thread(shape.worker.start)


async def _all_back(configs: dict[str, AgentConfig]) -> bool:
    """Every vehicle of ``configs`` is on an uplink again (in service or idle)."""
    statuses = await db(
        lambda: list(
            Vehicle.objects.filter(name__in=list(configs)).values_list("status", flat=True)
        )
    )
    return Vehicle.Status.OFFLINE not in statuses and len(statuses) == len(configs)
