"""Liveness off the database: heartbeats go to Redis, the row changes on a state change.

A real uplink (the wire protocol over channels' test communicator) and the real Redis
(bin/test); without Redis, liveness lives in the rows and these tests are skipped.
"""

from __future__ import annotations

import asyncio
from datetime import timedelta
from typing import Any

import pytest
from asgiref.sync import async_to_sync
from channels.db import database_sync_to_async
from channels.testing import WebsocketCommunicator
from django.utils import timezone

from accounts.roles import MONITOR
from fleet.liveness import Live, LivenessWriter, vehicles_fresh, vehicles_live, vehicles_seen
from fleet.models import UplinkServer, Vehicle
from fleet.status import vehicles_mark_stale_offline
from iouv.asgi import application
from tests import factories as f
from tests.uplink import agent_idle, connections_closed, eventually
from tests.vehicle_events import hearing

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.redis]

PROFILE: dict[str, Any] = {
    "type": "profile",
    "vehicle_type": "car",
    "adapter": "sim_car",
    "attributes": {},
    "commands": [{"name": "stop", "args": {}}],
    "telemetry": ["position", "battery"],
    "control_url": "ws://10.0.0.7:8765/control",
    "video": False,
    "position": {"lat": 40.63, "lon": -8.65, "alt": 0.0},
    "battery": 88,
}


@pytest.fixture(autouse=True)
async def _tidy(settings):
    # Heartbeats are throttled to two per interval: keep the interval short so the
    # tests' heartbeats are each handled.
    settings.IOUV_HEARTBEAT_INTERVAL_S = 0.02
    yield
    await connections_closed()


async def _beat(comm: WebsocketCommunicator, seq: int, **fields: Any) -> None:
    """Send a heartbeat and wait until the uplink has handled it (a bad frame sent after
    it is answered in turn, after what came before it)."""
    await asyncio.sleep(0.011)  # past the throttle of two per heartbeat interval
    await comm.send_json_to({"type": "heartbeat", "seq": seq, **fields})
    await comm.send_to(text_data="not json")
    assert (await comm.receive_json_from(timeout=10))["code"] == "bad_json"


def _row(vehicle: Vehicle) -> Vehicle:
    return Vehicle.objects.get(pk=vehicle.pk)


async def test_heartbeats_that_change_nothing_reach_redis_not_the_row():
    vehicle, comm = await agent_idle(PROFILE, within=10.0)
    before = await database_sync_to_async(_row)(vehicle)

    # Half a percent of battery and a few metres: news for the monitor, not the row.
    await _beat(comm, 1, battery=87.5, position={"lat": 40.63002, "lon": -8.65, "alt": 0.0})
    await eventually(
        lambda: vehicles_live([vehicle.pk])[str(vehicle.pk)].battery == 87.5, within=10.0
    )
    row = await database_sync_to_async(_row)(vehicle)
    assert (row.last_seen, row.battery, row.lat) == (before.last_seen, 88, 40.63)
    live = (await database_sync_to_async(vehicles_live)([vehicle.pk]))[str(vehicle.pk)]
    assert (live.battery, live.lat) == (87.5, 40.63002)
    seen = (await database_sync_to_async(vehicles_seen)([vehicle.pk]))[str(vehicle.pk)]
    assert seen > before.last_seen

    # A whole step of battery (from what the row holds): the row follows.
    await _beat(comm, 2, battery=86.9)
    row = await database_sync_to_async(_row)(vehicle)
    assert row.battery == 86.9 and row.last_seen > before.last_seen and row.lat == 40.63002

    # Thirty metres away: the row follows; a lost fix too.
    await _beat(comm, 3, position={"lat": 40.6306, "lon": -8.65, "alt": 0.0})
    assert (await database_sync_to_async(_row)(vehicle)).lat == 40.6306
    await _beat(comm, 4, position=None)
    assert (await database_sync_to_async(_row)(vehicle)).lat is None
    await comm.disconnect()


async def test_the_disconnect_stores_when_the_agent_was_last_heard():
    vehicle, comm = await agent_idle(PROFILE, within=10.0)
    profiled = (await database_sync_to_async(_row)(vehicle)).last_seen
    await _beat(comm, 1)  # nothing changed: Redis only
    await eventually(lambda: vehicles_seen([vehicle.pk])[str(vehicle.pk)] > profiled, within=10.0)
    heard = (await database_sync_to_async(vehicles_seen)([vehicle.pk]))[str(vehicle.pk)]
    await comm.disconnect()
    await eventually(lambda: _row(vehicle).status == "offline", within=10.0)
    assert abs((await database_sync_to_async(_row)(vehicle)).last_seen - heard) < timedelta(
        milliseconds=1
    )


def _write_live(entries: dict[str, Live]) -> None:
    async def write() -> None:
        writer = LivenessWriter()
        for pk, live in entries.items():
            writer.put(pk, live)
        await writer.close()

    async_to_sync(write)()


def test_the_sweep_reads_liveness_and_keeps_when_each_was_last_heard(settings):
    settings.IOUV_OFFLINE_AFTER_S = 5
    station, vtype = f.station(), f.vehicle_type()
    long_ago = timezone.now() - timedelta(seconds=60)
    heard_lately = f.vehicle(station=station, vtype=vtype, name="heard-lately")
    silent = f.vehicle(station=station, vtype=vtype, name="silent")
    never = f.vehicle(station=station, vtype=vtype, name="never-in-redis")
    # The rows are old (heartbeats no longer write them); Redis knows better.
    Vehicle.objects.filter(pk__in=[heard_lately.pk, silent.pk, never.pk]).update(last_seen=long_ago)
    silent_at = timezone.now() - timedelta(seconds=20)
    _write_live(
        {
            str(heard_lately.pk): Live(timezone.now().timestamp(), 50.0),
            str(silent.pk): Live(silent_at.timestamp(), 40.0),
        }
    )

    assert sorted(map(str, vehicles_mark_stale_offline())) == sorted(
        [str(silent.pk), str(never.pk)]
    )
    statuses = dict(Vehicle.objects.values_list("name", "status"))
    assert statuses == {"heard-lately": "idle", "silent": "offline", "never-in-redis": "offline"}
    assert abs(_row(silent).last_seen - silent_at) < timedelta(milliseconds=1)
    assert _row(never).last_seen == long_ago
    assert vehicles_fresh([heard_lately.pk, silent.pk, never.pk]) == {str(heard_lately.pk)}


async def test_a_vehicle_the_sweep_marked_offline_is_back_with_its_next_heartbeat():
    vehicle, comm = await agent_idle(PROFILE, within=10.0)
    with hearing("agent_disconnected") as gone:
        # As if the agent had gone silent: the sweep looks from a minute later, when
        # its uplink's process still beats (fleet.servers: a process gone would
        # excuse the silence).
        later = timezone.now() + timedelta(seconds=60)

        def sweep_later() -> list[Any]:
            UplinkServer.objects.update(alive_at=later)
            return vehicles_mark_stale_offline(now=later)

        marked = await database_sync_to_async(sweep_later)()
        assert [str(pk) for pk in marked] == [str(vehicle.pk)]
        assert (await database_sync_to_async(_row)(vehicle)).status == "offline"

        # Nothing in its heartbeats changed, yet the row hears of it again: the sweep
        # told the uplink (over the channel layer, so it may take a heartbeat or two).
        seq = 0
        while (await database_sync_to_async(_row)(vehicle)).status != "idle":
            seq += 1
            assert seq < 200, "the vehicle never came back"
            await _beat(comm, seq)

        # The uplink still owns the row: its disconnect marks the vehicle offline.
        await comm.disconnect()
        await eventually(lambda: _row(vehicle).status == "offline", within=10.0)
        assert [heard["vehicle_id"] for heard in gone] == [str(vehicle.pk)]


async def test_the_monitor_sees_heartbeats_that_do_not_reach_the_row(monkeypatch, settings):
    from channels import auth

    settings.IOUV_FLEET_FEED_LIVE_S = 0.05
    vehicle, agent = await agent_idle(PROFILE, within=10.0)
    monitor = await database_sync_to_async(f.user)(roles=(MONITOR,))

    async def the_monitor(scope: Any) -> Any:
        return monitor

    monkeypatch.setattr(auth, "get_user", the_monitor)
    feed = WebsocketCommunicator(
        application, "/ws/fleet/", headers=[(b"origin", b"http://127.0.0.1")]
    )
    assert (await feed.connect())[0]
    snapshot = await feed.receive_json_from(timeout=10)
    shown = {v["id"]: v for v in snapshot["vehicles"]}[str(vehicle.pk)]
    assert shown["battery"] == 88

    await _beat(agent, 1, battery=87.7, position={"lat": 40.63001, "lon": -8.65, "alt": 0.0})
    while True:
        update = await feed.receive_json_from(timeout=10)
        mine = [v for v in update["vehicles"] if v["id"] == str(vehicle.pk)]
        if mine and mine[0]["battery"] == 87.7:
            break
    assert not update["full"]
    assert mine[0]["position"]["lat"] == 40.63001 and mine[0]["status"] == "idle"
    assert mine[0]["last_seen"] > shown["last_seen"]
    assert (await database_sync_to_async(_row)(vehicle)).battery == 88  # the row: unchanged
    await feed.disconnect()
    await agent.disconnect()


async def test_while_redis_is_away_heartbeats_reach_the_row(monkeypatch):
    import redis

    vehicle, comm = await agent_idle(PROFILE, within=10.0)

    async def unreachable(self: LivenessWriter, batch: Any) -> None:
        raise redis.ConnectionError("Connection refused")

    monkeypatch.setattr(LivenessWriter, "_store", unreachable)
    before = await database_sync_to_async(_row)(vehicle)
    # Below the step: Redis only, but Redis refuses it, so the next one goes to the row
    # (the uplink does not wait for Redis: it hears of the refusal a moment later).
    seq = 0
    while (await database_sync_to_async(_row)(vehicle)).battery != 87.9:
        seq += 1
        assert seq < 200, "no heartbeat reached the row"
        await _beat(comm, seq, battery=87.9)
    assert (await database_sync_to_async(_row)(vehicle)).last_seen > before.last_seen
    await comm.disconnect()


def test_while_redis_is_away_reads_fall_back_on_the_rows(settings):
    vehicle = f.vehicle(station=f.station(), vtype=f.vehicle_type())
    settings.REDIS_URL = "redis://127.0.0.1:1/0"  # nothing listens there
    assert vehicles_seen([vehicle.pk]) == {str(vehicle.pk): _row(vehicle).last_seen}
    assert vehicles_live([vehicle.pk])[str(vehicle.pk)].battery == vehicle.battery
    assert vehicles_mark_stale_offline() == []
