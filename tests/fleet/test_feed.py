"""The monitors' live fleet feed over the channel layer (Redis in bin/test)."""

from __future__ import annotations

import pytest
from channels.db import database_sync_to_async
from channels.testing import WebsocketCommunicator

from accounts.roles import CLIENT, MONITOR
from fleet.status import vehicle_set_maintenance
from iouv.asgi import application
from tests import factories as f
from tests.uplink import connections_closed

pytestmark = pytest.mark.django_db(transaction=True)


@pytest.fixture(autouse=True)
async def _close_worker_connections():
    yield
    await connections_closed()


def _connect() -> WebsocketCommunicator:
    return WebsocketCommunicator(
        application, "/ws/fleet/", headers=[(b"origin", b"http://127.0.0.1")]
    )


def _scope_user_patch(monkeypatch, user):
    # AuthMiddlewareStack reads the user from the session cookie; give it ours.
    from channels import auth

    async def fake_get_user(scope):
        return user

    monkeypatch.setattr(auth, "get_user", fake_get_user)


async def test_monitor_gets_snapshot_then_changes(monkeypatch):
    monitor = await database_sync_to_async(f.user)(roles=(MONITOR,))
    vehicle = await database_sync_to_async(
        lambda: f.vehicle(station=f.station(), vtype=f.vehicle_type(), name="quad-1")
    )()
    _scope_user_patch(monkeypatch, monitor)
    comm = _connect()
    connected, _ = await comm.connect()
    assert connected
    snapshot = await comm.receive_json_from(timeout=5)
    assert snapshot["full"] and [v["name"] for v in snapshot["vehicles"]] == ["quad-1"]

    await database_sync_to_async(vehicle_set_maintenance)(vehicle=vehicle, on=True)
    update = await comm.receive_json_from(timeout=5)
    assert not update["full"]
    assert update["vehicles"][0]["status"] == "maintenance"

    await comm.send_json_to({"type": "stop"})
    assert (await comm.receive_json_from(timeout=5))["code"] == "read_only"
    await comm.disconnect()


async def test_client_is_refused(monkeypatch):
    client = await database_sync_to_async(f.user)(roles=(CLIENT,))
    _scope_user_patch(monkeypatch, client)
    comm = _connect()
    connected, code = await comm.connect()
    assert not connected and code == 4403
    await comm.disconnect()  # the consumer ends on this test's loop, its reads with it


async def test_foreign_origin_is_refused():
    comm = WebsocketCommunicator(
        application, "/ws/fleet/", headers=[(b"origin", b"http://evil.example")]
    )
    connected, _ = await comm.connect()
    assert not connected
    await comm.disconnect()
