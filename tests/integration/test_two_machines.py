"""Two machines behind one nginx, and one of them cut off (issue 39).

Machines A and B are network namespaces on a tests.netlab lab's bridge, each running
the platform's HTTP process (gunicorn) and WebSocket process (``python -m iouv.serve``)
on production's ports, reaching PostgreSQL and Redis (on this machine's loopback)
through the lab's forwarders. nginx (deploy/nginx/iouv.conf, TLS) spreads over both;
the Celery worker with its beat runs beside nginx, as do three cars' agents (nginx
spreads their uplinks over both machines), one user driving a car on its own socket,
one driving another over the platform's relay, and a program reading the API through
nginx.

Then the machine holding the uplink of the relayed user's car loses its network: its
veth goes down, and whatever it sends or is sent vanishes, nothing is closed (a pulled
cable, a dead switch). Every agent it held is back on an uplink through the other machine within
10 s of the cut (the agents' keepalive gives a silent uplink up, agents.uplink); the
sessions stay active past every supervision timer and no car changes status; the
direct user never misses a
command, the relayed one drives again, and the API never fails: with the upstream
settings docs/operations.md gives for several machines, nginx moves a request that
meets the dead machine to the other after ``proxy_connect_timeout`` and then skips it.
The times measured are printed (``pytest -s``).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from pathlib import Path
from urllib.parse import urlsplit

import pytest
from django.conf import settings

from accounts.tokens import token_issue
from agents.runtime import Agent
from fleet.models import UplinkServer, Vehicle
from services.models import Assignment, Session
from tests import factories as f
from tests.netlab import NetLab, netlab_available
from tests.production import Host, ProductionShape
from tests.production_clients import Driver, Reader, api, car_fleet, task_accepted
from tests.servers import agent_running, db, until

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.realtime,
    pytest.mark.django_db(transaction=True),
    pytest.mark.cost(30),
]

#: What the issue asks: the agents of a machine cut off are back through another
#: within this long.
RECONNECT_WITHIN_S = 10.0
#: The supervisor's timers, short. The grace an agent has to come back after its
#: process is gone (IOUV_AGENT_RECONNECT_S) is the bound above, not the default 30 s:
#: an agent not back in time would be offline, then lost, before the test ends.
TIMERS = {
    "IOUV_OFFLINE_AFTER_S": "2",
    "IOUV_HEARTBEAT_INTERVAL_S": "0.5",
    "IOUV_VEHICLE_LOST_S": "2",
    "IOUV_AGENT_RECONNECT_S": str(RECONNECT_WITHIN_S),
    "IOUV_RECONNECT_GRACE_S": "10",
    "IOUV_SUPERVISION_TICK_S": "0.5",
    # A transaction the cut machine had open keeps its row locks (the relayed
    # session's log, a car's row) until PostgreSQL ends it: a registration or a grant
    # through the other machine waits that long. Shorter than the default 10 s, so
    # the agents' 10 s bound holds wherever the cut falls.
    "DB_IDLE_IN_TRANSACTION_S": "3",
}
#: nginx's upstream servers on other machines, as docs/operations.md recommends: a
#: server that did not answer is skipped for 10 s, and the HTTP upstream keeps no idle
#: connections (a request sent on one to a machine cut off would wait for
#: proxy_read_timeout; a new connection fails after proxy_connect_timeout, 2 s).
SERVER_OPTIONS = "max_fails=1 fail_timeout=10s"
#: The slowest API answer after the cut: proxy_connect_timeout (2 s) once, with margin
#: for a loaded machine.
API_SLOWEST_S = 5.0
#: Past every timer above after the cut (the machine's last beat and a period; the
#: agents' grace; offline, then lost; a tick), with margin.
PAST_TIMERS_S = 18.0


def _machine_env(lab: NetLab) -> dict[str, str]:
    """The environment that makes a machine's processes use the root namespace's
    PostgreSQL and Redis through the lab's forwarders."""
    db = settings.DATABASES["default"]
    redis = urlsplit(settings.REDIS_URL)
    return {
        "DATABASE_URL": (
            f"postgres://{db.get('USER') or ''}@{lab.public_ip}:{db.get('PORT') or 5432}"
            f"/{db['NAME']}"
        ),
        "REDIS_URL": redis._replace(netloc=f"{lab.public_ip}:{redis.port or 6379}").geturl(),
    }


def _statuses() -> dict[str, str]:
    return dict(Vehicle.objects.values_list("name", "status"))


async def _holders(vehicles: list[Vehicle], shape: ProductionShape) -> dict[str, str]:
    """Each vehicle's id -> the name of the host whose WebSocket process holds its
    uplink ("?" when none yet), read from Vehicle.uplink_server and the server rows
    (named ``hostname:pid``; ``ip netns exec`` runs the server under the pid started)."""

    def read() -> dict[str, str]:
        by_pid = {str(p.proc.pid): p.name.removeprefix("uvicorn-") for p in shape.ws if p.proc}
        names = dict(UplinkServer.objects.values_list("pk", "name"))
        holders = {}
        for pk, server in Vehicle.objects.filter(pk__in=[v.pk for v in vehicles]).values_list(
            "pk", "uplink_server"
        ):
            name = names.get(server, "") if server is not None else ""
            holders[str(pk)] = by_pid.get(name.rpartition(":")[2], "?")
        return holders

    return await db(read)


async def test_a_machine_cut_off_hands_its_agents_to_the_other_within_10_s(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    available, why = netlab_available()
    if not available:
        pytest.skip(why)
    cars, credentials = await db(car_fleet, 3)
    alice = await db(lambda: token_issue(user=f.user(username="alice"), name="t"))
    bob = await db(lambda: token_issue(user=f.user(username="bob"), name="t"))
    # PostgreSQL and Redis listen on this machine's loopback, on these ports.
    services = [
        int(settings.DATABASES["default"].get("PORT") or 5432),
        urlsplit(settings.REDIS_URL).port or 6379,
    ]
    with (
        NetLab(machines=["a", "b"], workdir=tmp_path / "lab") as lab,
        lab.loopback_offered(services),
    ):
        hosts = [
            Host(
                name,
                lab.machine(name).ip,
                prefix=tuple(lab.command(name, [])),
                env=_machine_env(lab),
            )
            for name in ("a", "b")
        ]
        shape = ProductionShape(
            tmp_path,
            web=1,
            ws=1,
            env=TIMERS,
            hosts=hosts,
            server_options=SERVER_OPTIONS,
            upstream_keepalive=False,
        )
        # The agents (in this process) trust the test's CA, as a vehicle trusts the
        # platform's certificate.
        monkeypatch.setenv("SSL_CERT_FILE", str(shape.certificates.ca))
        with shape.running():
            async with contextlib.AsyncExitStack() as stack:
                agents: dict[str, Agent] = {}
                for car, credential in zip(cars, credentials, strict=True):
                    agents[str(car.pk)] = await stack.enter_async_context(
                        agent_running(
                            base=shape.base,
                            vehicle=car,
                            credential=credential,
                            adapter="car",
                            options={"origin": list(f.HOME)},
                        )
                    )

                async def all_idle() -> bool:
                    statuses = await db(
                        lambda: set(Vehicle.objects.values_list("status", flat=True))
                    )
                    return statuses == {Vehicle.Status.IDLE}

                await until(all_idle, within=30, what="the agents registered through nginx")

                sessions, drivers = [], []
                for token, direct in ((alice, True), (bob, False)):
                    status, body = await asyncio.to_thread(
                        api, shape.base, shape.context, "POST", "/sessions", token
                    )
                    assert status == 201, body
                    sessions.append(body["session"]["id"])
                    await task_accepted(body["session"]["id"])
                    drivers.append(Driver(shape, token, body["task"], direct=direct))
                reader = Reader(shape, alice)
                try:
                    for driver in drivers:
                        await driver.until_acked(5)
                    relayed_car = await db(
                        lambda: str(
                            Assignment.objects.get(session_id=sessions[1], active=True).vehicle_id
                        )
                    )
                    await _cut_and_recover(
                        lab, shape, cars, agents, drivers, reader, alice, relayed_car
                    )
                    for session_id in sessions:
                        session = await db(Session.objects.get, pk=session_id)
                        assert session.state == Session.State.ACTIVE, session.reason
                finally:
                    await reader.stop()
                    for driver in drivers:
                        await driver.stop()


async def _cut_and_recover(
    lab: NetLab,
    shape: ProductionShape,
    cars: list[Vehicle],
    agents: dict[str, Agent],
    drivers: list[Driver],
    reader: Reader,
    alice_token: str,
    relayed_car: str,
) -> None:
    """Cut off the machine holding ``relayed_car``'s uplink; assert what the module
    promises."""
    direct_driver, relayed = drivers
    holders = await _holders(cars, shape)
    assert "?" not in holders.values(), holders
    cut = holders[relayed_car]
    other = "b" if cut == "a" else "a"
    moved = [pk for pk, host in holders.items() if host == cut]
    before = {pk: agents[pk].uplink.connections for pk in moved}
    on_cut = [p for p in [*shape.web, *shape.ws] if p.host == lab.machine(cut).ip]
    # Two cars in service (the users'), one idle: as they will be after the cut.
    statuses_before = await db(_statuses)
    assert sorted(statuses_before.values()) == sorted(
        [Vehicle.Status.IDLE] + [Vehicle.Status.IN_SERVICE] * 2
    ), statuses_before

    cut_at = time.monotonic()
    lab.link_down(cut)
    # A program that starts reading the API after the cut (``reader`` may have had a
    # request in flight on the machine cut off: that one waits for nginx's
    # proxy_read_timeout, as with any proxy).
    after = Reader(shape, alice_token)
    try:
        back_after: dict[str, float] = {}

        async def back(pk: str) -> None:
            uplink = agents[pk].uplink

            async def registered_again() -> bool:
                # A new registration: the cut uplink given up, a fresh one welcomed...
                return uplink.connections > before[pk] and uplink.connected.is_set()

            what = f"{pk}'s agent registered again after machine {cut} was cut off"
            await until(registered_again, within=RECONNECT_WITHIN_S + 20, what=what)
            back_after[pk] = round(time.monotonic() - cut_at, 2)

        await asyncio.gather(*(back(pk) for pk in moved))
        print(f"machine {cut} cut off; its agents back after {back_after} s")
        slowest = max(back_after.values())
        assert slowest <= RECONNECT_WITHIN_S, f"agents back after {back_after} s"

        # ...through the other machine's process.
        async def all_on_other() -> bool:
            now = await _holders(cars, shape)
            return all(now[pk] == other for pk in moved)

        await until(all_on_other, within=10, what=f"the agents' uplinks held on {other}")

        # Past every supervision timer: the sessions go on, the cars in service, the
        # direct user never missed a command, the relayed one drives again.
        while time.monotonic() - cut_at < PAST_TIMERS_S:
            await direct_driver.until_acked(1)
        await relayed.until_acked(5)
        assert await db(_statuses) == statuses_before
        assert direct_driver.sent - direct_driver.acked <= 1
        gap = relayed.longest_gap(cut_at)
        print(f"relayed driving stopped for at most {gap:.1f} s; log {relayed.log}")
        assert gap <= RECONNECT_WITHIN_S + 5, f"relayed driving stopped {gap:.1f} s"
        assert reader.failures == [], reader.failures[:5]
        # A request that meets the cut machine waits proxy_connect_timeout (2 s) and goes
        # to the other; the machine is then skipped for fail_timeout (SERVER_OPTIONS).
        took = [t for _asked, t in after.answered_at]
        print(
            f"API after the cut: {len(took)} answers, slowest {max(took, default=0):.2f} s, "
            f"{sum(t > 1.5 for t in took)} over 1.5 s; the reader running at the cut: "
            f"{sum(asked > cut_at for asked, _ in reader.answered_at)} answers since"
        )
        assert after.failures == [], after.failures[:5]
        assert len(took) >= 10 and max(took) <= API_SLOWEST_S, took
    finally:
        await after.stop()
        # A machine cut off cannot be stopped gracefully (its shutdown would wait on
        # sockets and a database nobody answers): it goes as a dead machine does.
        for process in on_cut:
            if process.proc is not None and process.proc.poll() is None:
                process.proc.kill()
                process.proc.wait(10)
