"""A vehicle's agent played in this process on the platform's uplink, through channels'
``WebsocketCommunicator`` on the ASGI application: the vehicle enrolled, its uplink
opened, hello said, the welcome received, the profile sent; and waiting until the
database says something, read on the ORM's thread.

Tests that play the agent this way are ``django_db(transaction=True)``: the consumer
reads and writes on asgiref's worker thread, outside the test's transaction.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any

from channels.db import database_sync_to_async
from channels.layers import get_channel_layer
from channels.testing import WebsocketCommunicator
from django.db import connections

from agents.protocol import PROTOCOL_VERSION
from fleet.credentials import vehicle_issue_credential
from fleet.models import Vehicle
from iouv.asgi import application
from tests import factories as f

#: How long closing the channel layer's pools may take at a test's end.
LAYER_CLOSE_S = 15.0


async def connections_closed() -> None:
    """At the end of a test that played clients on the ASGI application: close the ORM's
    connections of asgiref's worker thread (which would outlive the test and block
    dropping its database), and the Redis channel layer's pools of this event loop (so
    closing the loop does not wait on their blocking reads).

    Closing the pools first waits for the layer's clean-ups of cancelled receives (one
    started on an earlier test's loop, now closed, would never end): bounded, a wait
    that does not end is this test's error, not a worker held until pytest-timeout ends
    it without a word."""
    await database_sync_to_async(connections.close_all)()
    layer = get_channel_layer()
    if hasattr(layer, "close_pools"):
        try:
            async with asyncio.timeout(LAYER_CLOSE_S):
                await layer.close_pools()
        except TimeoutError:
            raise AssertionError(
                f"the channel layer's pools did not close within {LAYER_CLOSE_S:g} s: its "
                "clean-ups of cancelled receives did not end (a consumer left running on an "
                "earlier test's loop?)"
            ) from None


@database_sync_to_async
def vehicle_enrolled(**attributes: Any) -> tuple[Vehicle, str]:
    """A vehicle at a station of its own, offline (no agent yet), with ``attributes``
    (tests.factories.vehicle's); and the credential its agent says hello with."""
    vehicle = f.vehicle(station=f.station(), vtype=f.vehicle_type(), online=False, **attributes)
    return vehicle, vehicle_issue_credential(vehicle=vehicle)


async def uplink_open() -> WebsocketCommunicator:
    """A new uplink, connected, that has said nothing yet."""
    comm = WebsocketCommunicator(application, "/ws/agent/")
    connected, _ = await comm.connect()
    assert connected
    return comm


async def uplink_hello(vehicle: Vehicle, credential: str) -> WebsocketCommunicator:
    """A new uplink that has said hello as ``vehicle`` with ``credential``."""
    comm = await uplink_open()
    await comm.send_json_to(
        {
            "type": "hello",
            "v": PROTOCOL_VERSION,
            "vehicle_id": str(vehicle.pk),
            "credential": credential,
        }
    )
    return comm


async def uplink_welcomed(
    vehicle: Vehicle, credential: str, *, within: float = 5.0
) -> tuple[WebsocketCommunicator, dict[str, Any]]:
    """An authenticated uplink (its welcome came within ``within`` seconds), and the
    platform's welcome."""
    comm = await uplink_hello(vehicle, credential)
    welcome = await comm.receive_json_from(timeout=within)
    assert welcome["type"] == "welcome", welcome
    return comm, welcome


async def eventually(check: Callable[[], bool], *, within: float = 5.0) -> None:
    """Wait (up to ``within`` seconds) until ``check()``, run on the ORM thread, is
    true."""
    deadline = time.monotonic() + within
    while not await database_sync_to_async(check)():
        assert time.monotonic() < deadline, "condition not reached in time"
        await asyncio.sleep(0.02)


async def agent_idle(
    profile: dict[str, Any], *, within: float = 5.0
) -> tuple[Vehicle, WebsocketCommunicator]:
    """An enrolled vehicle whose agent said hello and sent ``profile``, once the
    platform has it idle; each step within ``within`` seconds."""
    vehicle, credential = await vehicle_enrolled()
    comm, _ = await uplink_welcomed(vehicle, credential, within=within)
    await comm.send_json_to(profile)
    await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).status == "idle", within=within)
    return vehicle, comm
