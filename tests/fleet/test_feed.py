"""The monitors' live fleet feed over the channel layer (Redis in bin/test)."""

from __future__ import annotations

import pytest
from channels.db import database_sync_to_async
from channels.layers import get_channel_layer
from channels.testing import WebsocketCommunicator
from django.db import connections

from accounts.roles import CLIENT, MONITOR
from fleet.status import vehicle_set_maintenance
from iouv.asgi import application
from tests import factories as f

pytestmark = pytest.mark.django_db(transaction=True)


@pytest.fixture(autouse=True)
async def _close_worker_connections():
    # Sync ORM calls run on asgiref's shared worker thread, whose connection would
    # otherwise outlive the test and block dropping the test database.
    yield
    await database_sync_to_async(connections.close_all)()
    # The Redis layer keeps a blocking read per consumer; close its pools on this
    # loop so closing the loop does not wait on them.
    layer = get_channel_layer()
    if hasattr(layer, "close_pools"):
        await layer.close_pools()


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


async def test_foreign_origin_is_refused():
    comm = WebsocketCommunicator(
        application, "/ws/fleet/", headers=[(b"origin", b"http://evil.example")]
    )
    connected, _ = await comm.connect()
    assert not connected
