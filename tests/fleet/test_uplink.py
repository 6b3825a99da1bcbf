"""The agent uplink, driven over the real wire protocol by a test 'agent'.

The channel layer is Redis under bin/test and in-memory under plain pytest.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
import time
from typing import Any

import pytest
from channels.db import database_sync_to_async
from channels.layers import get_channel_layer
from channels.testing import WebsocketCommunicator
from django.db import connections
from hypothesis import HealthCheck, given
from hypothesis import settings as hsettings
from hypothesis import strategies as st

from agents.protocol import MAX_MESSAGE_BYTES, MESSAGE_TYPES, PROTOCOL_VERSION, ProtocolError
from agents.protocol.messages import (
    EndTask,
    Event,
    RelayClose,
    Revoke,
    Task,
    TaskAccepted,
    TaskRefused,
    message_to_dict,
)
from fleet import uplink
from fleet.credentials import vehicle_issue_credential
from fleet.models import AgentMessage, Vehicle
from fleet.outbox import outbox
from fleet.sending import avehicle_send, vehicle_send
from fleet.uplink import vehicle_record_disconnect
from services.sessions.signing import platform_jwks, platform_public_key_pem
from tests.uplink import (
    agent_idle,
    eventually,
    uplink_hello,
    uplink_open,
    uplink_welcomed,
    vehicle_enrolled,
)
from tests.vehicle_events import hearing

#: One database for the module (conftest's ``module_database``): every test enrols
#: vehicles of its own and looks only at those, so the database is emptied once, after
#: the module, not after each test (2 s apiece).
pytestmark = pytest.mark.usefixtures("module_database")

PROFILE: dict[str, Any] = {
    "type": "profile",
    "vehicle_type": "drone",
    "adapter": "sim_drone",
    "attributes": {"cameras": ["rgb"]},
    "commands": [
        {"name": "up", "args": {}},
        {"name": "stop", "args": {}},
    ],
    "telemetry": ["position", "battery"],
    "control_url": "ws://10.0.0.7:8765/control",
    "video": True,
    "safe_actions": {"return_to_home": "fly back to its home point and land"},
    "position": {"lat": 40.63, "lon": -8.65, "alt": 12.5},
    "battery": 88,
}


@pytest.fixture(autouse=True)
async def _close_worker_connections():
    # Sync ORM calls run on asgiref's shared worker thread, whose connection would
    # otherwise outlive the test and block dropping the test database.
    yield
    await database_sync_to_async(connections.close_all)()


@database_sync_to_async
def _get(vehicle: Vehicle) -> Vehicle:
    return Vehicle.objects.get(pk=vehicle.pk)


@database_sync_to_async
def _update(vehicle: Vehicle, **fields: Any) -> None:
    Vehicle.objects.filter(pk=vehicle.pk).update(**fields)


async def _closed(comm: WebsocketCommunicator) -> tuple[list[dict], int]:
    """Everything sent until the platform closed the socket, and the close code."""
    messages = []
    while True:
        out = await comm.receive_output(timeout=5)
        if out["type"] == "websocket.close":
            # As a server would: the client's close handshake ends the consumer cleanly.
            await comm.disconnect()
            return messages, out.get("code")
        messages.append(json.loads(out["text"]))


async def _hello_closed(vehicle: Vehicle, credential: str) -> tuple[list[dict], int]:
    """Say hello on a new uplink that the platform is expected to close: what it sent,
    and the close code."""
    return await _closed(await uplink_hello(vehicle, credential))


# --- authentication ---------------------------------------------------------------------


async def test_good_hello_gets_welcome(settings):
    vehicle, credential = await vehicle_enrolled()
    comm, welcome = await uplink_welcomed(vehicle, credential)
    assert welcome["v"] == PROTOCOL_VERSION
    assert welcome["heartbeat_interval_s"] == settings.IOUV_HEARTBEAT_INTERVAL_S
    assert welcome["platform_public_key"] == await database_sync_to_async(platform_public_key_pem)()
    # The key set agents adopt (a key rotation reaches them this way).
    assert welcome["platform_jwks"] == await database_sync_to_async(platform_jwks)()
    assert (await _get(vehicle)).last_seen is not None
    await comm.disconnect()


@pytest.mark.parametrize("which", ["credential", "vehicle"])
async def test_bad_credential_is_closed_4401(which):
    vehicle, credential = await vehicle_enrolled()
    comm = await uplink_open()
    hello = {
        "type": "hello",
        "v": PROTOCOL_VERSION,
        "vehicle_id": str(vehicle.pk),
        "credential": credential,
    }
    if which == "credential":
        hello["credential"] = credential + "x"
    else:
        hello["vehicle_id"] = "00000000-0000-0000-0000-000000000000"
    await comm.send_json_to(hello)
    messages, code = await _closed(comm)
    assert code == 4401
    assert messages == [
        {"type": "error", "code": "bad_credential", "message": messages[0]["message"]}
    ]
    assert (await _get(vehicle)).last_seen is None


async def test_wrong_version_is_closed_4400():
    vehicle, credential = await vehicle_enrolled()
    comm = await uplink_open()
    # A v1 agent (signed documents before JWTs) meeting this platform is refused at hello.
    await comm.send_json_to(
        {"type": "hello", "v": 1, "vehicle_id": str(vehicle.pk), "credential": credential}
    )
    messages, code = await _closed(comm)
    assert code == 4400 and messages[0]["code"] == "bad_version"


@pytest.mark.parametrize(
    "frame",
    [
        "not json",
        json.dumps({"type": "heartbeat", "seq": 1}),
        json.dumps({"type": "hello", "v": PROTOCOL_VERSION}),
    ],
    ids=["garbage", "heartbeat-first", "incomplete-hello"],
)
async def test_anything_but_a_valid_hello_first_is_closed_4401(frame):
    comm = await uplink_open()
    await comm.send_to(text_data=frame)
    messages, code = await _closed(comm)
    assert code == 4401 and messages[0]["type"] == "error"


async def test_silent_connection_is_closed(settings):
    settings.IOUV_HELLO_TIMEOUT_S = 0.1
    comm = await uplink_open()
    messages, code = await _closed(comm)
    assert code == 4408 and messages[0]["code"] == "hello_timeout"


# --- registration and heartbeats -------------------------------------------------------


async def test_profile_makes_the_vehicle_idle_with_its_control_url():
    vehicle, credential = await vehicle_enrolled()
    with hearing("agent_connected") as connected:
        comm, _ = await uplink_welcomed(vehicle, credential)
        assert (await _get(vehicle)).status == Vehicle.Status.OFFLINE  # hello alone is not enough
        await comm.send_json_to(PROFILE)
        await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).status == "idle")
        stored = await _get(vehicle)
        assert stored.control_url == PROFILE["control_url"]
        assert stored.profile["commands"] == PROFILE["commands"]
        assert stored.profile["telemetry"] == ["position", "battery"]
        assert stored.profile["video"] is True and stored.profile["adapter"] == "sim_drone"
        assert stored.profile["safe_actions"] == PROFILE["safe_actions"]
        assert (stored.lat, stored.lon, stored.alt, stored.battery) == (40.63, -8.65, 12.5, 88)
        assert connected == [
            {
                "vehicle_id": str(vehicle.pk),
                "state": {"session_id": None, "controller": False, "status": None},
            }
        ]
        await comm.disconnect()


@pytest.mark.parametrize(
    ("before", "maintenance", "after"),
    [
        ("failsafe", False, "idle"),
        ("reserved", False, "reserved"),
        ("in_service", False, "in_service"),
        ("maintenance", True, "maintenance"),
    ],
)
async def test_profile_keeps_platform_held_statuses(before, maintenance, after):
    vehicle, credential = await vehicle_enrolled()
    await _update(vehicle, status=before, maintenance=maintenance)
    comm, _ = await uplink_welcomed(vehicle, credential)
    await comm.send_json_to(PROFILE)
    await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).control_url != "")
    assert (await _get(vehicle)).status == after
    await comm.disconnect()
    # An uplink going away never takes a vehicle out of maintenance.
    if maintenance:
        assert (await _get(vehicle)).status == "maintenance"


async def test_heartbeats_update_last_seen_battery_and_status(settings):
    settings.IOUV_HEARTBEAT_INTERVAL_S = 0.2  # one write per 0.1 s at most
    vehicle, comm = await agent_idle(PROFILE)
    seen_at = (await _get(vehicle)).last_seen

    await asyncio.sleep(0.15)
    await comm.send_json_to(
        {"type": "heartbeat", "seq": 1, "battery": 70, "position": {"lat": 40.7, "lon": -8.6}}
    )
    await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).battery == 70)
    stored = await _get(vehicle)
    assert stored.last_seen > seen_at and (stored.lat, stored.lon, stored.alt) == (40.7, -8.6, None)

    # Too soon after the last write: skipped, the next one carries fresher data anyway.
    await comm.send_json_to({"type": "heartbeat", "seq": 2, "battery": 60})
    await asyncio.sleep(0.15)
    await comm.send_json_to({"type": "heartbeat", "seq": 3, "battery": 50, "status": "failsafe"})
    await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).battery == 50)
    assert (await _get(vehicle)).status == "failsafe"

    await asyncio.sleep(0.15)
    await comm.send_json_to({"type": "heartbeat", "seq": 4, "status": "idle"})
    await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).status == "idle")
    await comm.disconnect()


async def test_heartbeat_flood_is_throttled(settings):
    settings.IOUV_HEARTBEAT_INTERVAL_S = 60.0
    vehicle, credential = await vehicle_enrolled()
    comm, _ = await uplink_welcomed(vehicle, credential)
    await comm.send_json_to(PROFILE)
    for seq in range(1, 30):
        await comm.send_json_to({"type": "heartbeat", "seq": seq, "battery": seq})
    await comm.send_to(text_data="sync")  # answered once everything before it was handled
    assert (await comm.receive_json_from(timeout=5))["code"] == "bad_json"
    assert (await _get(vehicle)).battery == 1  # only the first heartbeat was written
    await comm.disconnect()


async def test_heartbeats_of_many_uplinks_are_written_together(monkeypatch):
    # A thousand agents heartbeat 500 times a second; one transaction each kept the
    # platform behind. Heartbeats that arrive while a write is in flight share the next.
    batches: list[int] = []
    real = uplink.vehicle_record_heartbeats

    def counted(beats):
        batches.append(len(beats))
        return real(beats)

    monkeypatch.setattr(uplink, "vehicle_record_heartbeats", counted)
    agents = []
    for _ in range(30):
        vehicle, credential = await vehicle_enrolled()
        comm, _ = await uplink_welcomed(vehicle, credential)
        await comm.send_json_to(PROFILE)
        agents.append((vehicle, comm))
    ids = [vehicle.pk for vehicle, _ in agents]
    await eventually(lambda: Vehicle.objects.filter(pk__in=ids, status="idle").count() == 30)

    for n, (_, comm) in enumerate(agents):
        await comm.send_json_to({"type": "heartbeat", "seq": 1, "battery": n})
    await eventually(
        lambda: (
            sorted(Vehicle.objects.filter(pk__in=ids).values_list("battery", flat=True))
            == list(range(30))
        )
    )
    assert sum(batches) == 30
    assert len(batches) < 10, batches  # 30 separate transactions would be the old way
    for _, comm in agents:
        await comm.disconnect()


async def test_a_failed_heartbeat_write_is_an_error_reply_not_a_lost_uplink(monkeypatch):
    from django.db import OperationalError

    vehicle, comm = await agent_idle(PROFILE)
    real = uplink.vehicle_record_heartbeats

    def failing(beats):
        raise OperationalError("deadlock detected")

    monkeypatch.setattr(uplink, "vehicle_record_heartbeats", failing)
    await comm.send_json_to({"type": "heartbeat", "seq": 1, "battery": 12})
    reply = await comm.receive_json_from(timeout=5)
    assert reply["type"] == "error" and reply["code"] == "internal", reply
    assert (await _get(vehicle)).battery == PROFILE["battery"]

    # The database is back: the same uplink's next heartbeat is stored.
    monkeypatch.setattr(uplink, "vehicle_record_heartbeats", real)
    await asyncio.sleep(float(uplink.settings.IOUV_HEARTBEAT_INTERVAL_S) / 2)
    await comm.send_json_to({"type": "heartbeat", "seq": 2, "battery": 13})
    await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).battery == 13)
    await comm.disconnect()


@pytest.mark.parametrize("slow", ["heartbeat write", "shared database thread"])
async def test_relay_traffic_does_not_wait_for_a_slow_database(monkeypatch, slow):
    # Relayed answers and everything sent to the agent are on the control path: neither
    # a heartbeat write stuck behind a lock nor another consumer's work on the process's
    # one thread for synchronous database calls may hold them.
    vehicle, comm = await agent_idle(PROFILE)
    entered, release = threading.Event(), threading.Event()

    def hold() -> None:
        entered.set()
        release.wait(10)

    busy = None
    if slow == "heartbeat write":
        real = uplink.vehicle_record_heartbeats

        def stuck(beats):
            hold()
            return real(beats)

        monkeypatch.setattr(uplink, "vehicle_record_heartbeats", stuck)
        await comm.send_json_to({"type": "heartbeat", "seq": 1, "battery": 40})
    else:
        busy = asyncio.create_task(database_sync_to_async(hold)())
    assert await asyncio.to_thread(entered.wait, 5)
    layer = get_channel_layer()
    browser = await layer.new_channel()
    await layer.group_add(uplink.relay_group("c0ffee"), browser)
    try:
        answer = {"type": "ack", "seq": 7, "ok": True, "error": None}
        await comm.send_json_to(
            {"type": "relay", "session_id": "s-1", "conn": "c0ffee", "payload": answer}
        )
        event = await asyncio.wait_for(layer.receive(browser), 2)
        assert json.loads(event["text"]) == answer and not release.is_set()

        revoke = RelayClose(session_id="s-1", conn="c0ffee", reason="kill")
        await avehicle_send(vehicle_id=vehicle.pk, message=revoke)
        assert await comm.receive_json_from(timeout=2) == message_to_dict(revoke)
        assert not release.is_set()  # the database work is still held
    finally:
        release.set()
        await layer.group_discard(uplink.relay_group("c0ffee"), browser)
        if busy is not None:
            await busy
    if slow == "heartbeat write":
        await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).battery == 40)
    await comm.disconnect()


async def test_a_server_cancelling_the_uplink_leaves_none_of_its_tasks_pending():
    # A server shutting down cancels its application instances, without a disconnect.
    # The uplink's own tasks (the hello deadline, the database backlog) must end with it,
    # not be destroyed pending when the loop closes.
    _, comm = await agent_idle(PROFILE)
    mine = {t for t in asyncio.all_tasks() if t.get_coro().__qualname__.startswith("AgentUplink")}
    assert mine, "the uplink runs its backlog in a task of its own"
    comm.future.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await comm.future
    await asyncio.sleep(0)
    assert all(t.done() for t in mine), [t for t in mine if not t.done()]


async def test_what_the_agent_said_before_leaving_is_stored_before_the_offline_mark(
    monkeypatch,
):
    vehicle, comm = await agent_idle(PROFILE)
    real = uplink.vehicle_record_heartbeats

    def slow(beats):
        time.sleep(0.5)
        return real(beats)

    monkeypatch.setattr(uplink, "vehicle_record_heartbeats", slow)
    await comm.send_json_to({"type": "heartbeat", "seq": 1, "battery": 41})
    await comm.disconnect(code=1001)
    # The heartbeat went in first, so the offline mark is the last word.
    await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).status == "offline")
    await asyncio.sleep(0.6)
    stored = await _get(vehicle)
    assert stored.status == "offline" and stored.battery == 41


async def test_a_lost_push_does_not_lose_the_disconnect(monkeypatch):
    # A thousand uplinks dropping at once once exhausted the channel layer's pool: the
    # monitors' push of the offline mark failed after the commit, and that error
    # skipped the rest, so the sessions never logged their vehicle going offline.
    from redis.exceptions import MaxConnectionsError

    vehicle, credential = await vehicle_enrolled()
    with hearing("agent_disconnected") as gone:
        comm, _ = await uplink_welcomed(vehicle, credential)
        await comm.send_json_to(PROFILE)
        await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).status == "idle")
        layer = get_channel_layer()
        real_send = layer.group_send

        async def failing(group, message):
            if group == "fleet":
                raise MaxConnectionsError("Too many connections")
            await real_send(group, message)

        monkeypatch.setattr(layer, "group_send", failing)
        await comm.disconnect(code=1006)
        await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).status == "offline")
        await eventually(lambda: len(gone) == 1)
        assert gone == [{"vehicle_id": str(vehicle.pk), "code": 1006}]


async def test_disconnect_marks_offline_and_tells_the_session_owner():
    vehicle, credential = await vehicle_enrolled()
    with hearing("agent_disconnected") as gone:
        comm, _ = await uplink_welcomed(vehicle, credential)
        await comm.send_json_to(PROFILE)
        await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).status == "idle")
        await comm.disconnect(code=1001)
        await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).status == "offline")
        assert gone == [{"vehicle_id": str(vehicle.pk), "code": 1001}]


async def test_a_stale_uplink_does_not_mark_a_reconnected_vehicle_offline():
    vehicle, _ = await vehicle_enrolled()
    await _update(vehicle, status="idle")
    stored = await _get(vehicle)
    old = stored.last_seen
    # A newer uplink wrote since: the old uplink's late disconnect changes nothing.
    from django.utils import timezone

    await _update(vehicle, last_seen=timezone.now())
    assert not await database_sync_to_async(vehicle_record_disconnect)(
        vehicle_id=vehicle.pk, last_seen=old
    )
    assert (await _get(vehicle)).status == "idle"


# --- bad input after authentication -----------------------------------------------------


@pytest.mark.parametrize(
    ("frame", "code"),
    [
        ({"text_data": "{not json"}, "bad_json"),
        ({"text_data": "[1, 2]"}, "bad_json"),
        ({"text_data": json.dumps({"type": "launch_missiles"})}, "unknown_type"),
        ({"text_data": json.dumps({"type": "heartbeat", "seq": -1})}, "bad_field"),
        ({"text_data": json.dumps({"type": "x", "pad": "a" * MAX_MESSAGE_BYTES})}, "too_large"),
        ({"bytes_data": b"\xff\xfe\x00garbage"}, "bad_json"),
        (
            {
                "text_data": json.dumps(
                    {"type": "hello", "v": PROTOCOL_VERSION, "vehicle_id": "a", "credential": "b"}
                )
            },
            "already_authenticated",
        ),
    ],
    ids=["json", "not-object", "unknown-type", "bad-field", "oversized", "binary", "hello-again"],
)
async def test_bad_frame_gets_an_error_and_the_uplink_stays(frame, code):
    vehicle, credential = await vehicle_enrolled()
    comm, _ = await uplink_welcomed(vehicle, credential)
    await comm.send_to(**frame)
    reply = await comm.receive_json_from(timeout=5)
    assert reply["type"] == "error" and reply["code"] == code
    assert len(reply["message"]) <= 300
    # Still connected and still working: a valid heartbeat (binary, as the protocol
    # allows) is stored.
    await comm.send_to(
        bytes_data=json.dumps({"type": "heartbeat", "seq": 1, "battery": 42}).encode()
    )
    await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).battery == 42)
    await comm.disconnect()


async def test_flood_of_bad_frames_is_closed_4429():
    vehicle, credential = await vehicle_enrolled()
    comm, _ = await uplink_welcomed(vehicle, credential)
    for _ in range(uplink.BAD_FRAMES_MAX - 1):
        await comm.send_to(text_data="nope")
        assert (await comm.receive_json_from(timeout=5))["code"] == "bad_json"
    await comm.send_to(text_data="nope")
    messages, code = await _closed(comm)
    assert code == 4429 and messages[0]["code"] == "flood"


# --- one agent per vehicle --------------------------------------------------------------


async def test_second_connection_replaces_the_first():
    vehicle, credential = await vehicle_enrolled()
    first, _ = await uplink_welcomed(vehicle, credential)
    await first.send_json_to(PROFILE)
    await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).status == "idle")

    second, _ = await uplink_welcomed(vehicle, credential)
    messages, code = await _closed(first)
    assert code == 4409 and messages[0]["code"] == "replaced"
    await second.send_json_to(PROFILE)
    await second.send_to(text_data="sync")
    await second.receive_json_from(timeout=5)
    # The replaced uplink's disconnect did not take the vehicle offline...
    assert (await _get(vehicle)).status == "idle"
    # ... and messages for the vehicle reach the new uplink only.
    await avehicle_send(
        vehicle_id=vehicle.pk, message=RelayClose(session_id="s-1", conn="c0ffee", reason="done")
    )
    assert (await second.receive_json_from(timeout=5))["type"] == "relay_close"
    await second.disconnect()
    await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).status == "offline")


# --- platform -> agent, agent -> platform ------------------------------------------------


SESSION = "5b0d6c0e-8a3c-4d7e-9a51-0c4f1f2b7a10"
REVOKE = Revoke(session_id=SESSION, reason="kill switch", action="land")


@database_sync_to_async
def _owe(vehicle: Vehicle, message: Task | Revoke | EndTask) -> None:
    """Owe ``message`` to the vehicle's agent, committed (as a view or a worker does)."""
    vehicle_send(vehicle_id=vehicle.pk, message=message)


@database_sync_to_async
def _message_state(vehicle: Vehicle) -> list[str]:
    owed = AgentMessage.objects.filter(vehicle_id=vehicle.pk).exclude(kind="disconnect")
    return list(owed.values_list("state", flat=True))


async def test_an_owed_message_reaches_the_agent_with_an_id_until_acknowledged():
    vehicle, comm = await agent_idle(PROFILE)
    await _owe(vehicle, REVOKE)
    first = await comm.receive_json_from(timeout=5)
    assert first == {**message_to_dict(REVOKE), "id": first["id"]}
    # Not acknowledged: it comes again, with the same id, so the agent can tell.
    again = await comm.receive_json_from(timeout=5)
    assert again == first
    await comm.send_json_to({"type": "ack", "id": first["id"], "ok": True})
    await eventually(
        lambda: AgentMessage.objects.get(vehicle_id=vehicle.pk).state == AgentMessage.State.ACKED
    )
    assert await outbox().deliver_due() == 0  # acknowledged: owed no more
    assert await comm.receive_nothing(timeout=0.3)
    await comm.disconnect()


async def test_a_message_owed_while_the_agent_is_away_is_delivered_when_it_is_back():
    vehicle, comm = await agent_idle(PROFILE)
    await comm.disconnect()
    await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).status == "offline")
    await _owe(vehicle, REVOKE)
    credential = await database_sync_to_async(vehicle_issue_credential)(vehicle=vehicle)
    back, _ = await uplink_welcomed(vehicle, credential)
    await back.send_json_to({**PROFILE, "session_id": SESSION})
    message = await back.receive_json_from(timeout=5)
    assert message == {**message_to_dict(REVOKE), "id": message["id"]}
    # Until it confirms, the vehicle is busy with the session it still runs.
    assert (await _get(vehicle)).status == Vehicle.Status.RELEASING
    await back.send_json_to({"type": "ack", "id": message["id"], "ok": True})
    await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).status == "idle")
    assert await _message_state(vehicle) == ["acked"]
    await back.disconnect()


async def test_a_replaced_credential_closes_the_live_uplink_within_a_second():
    vehicle, comm = await agent_idle(PROFILE)
    started = time.monotonic()
    await database_sync_to_async(vehicle_issue_credential)(vehicle=vehicle)
    messages, code = await _closed(comm)
    assert time.monotonic() - started < 1.0
    assert code == 4401 and messages[-1]["code"] == "credential_revoked"


async def test_a_replaced_credential_closes_the_uplink_without_the_channel_layer(monkeypatch):
    """The database alone carries the word: the nudge through the broker is lost."""
    from fleet import outbox as outbox_module

    monkeypatch.setattr(outbox_module, "get_channel_layer", lambda: None)
    vehicle, comm = await agent_idle(PROFILE)
    # As if another process (a worker) issued it: this process's outbox is not woken.
    monkeypatch.setattr(outbox_module, "_outboxes", {})
    await database_sync_to_async(vehicle_issue_credential)(vehicle=vehicle)
    _, code = await _closed(comm)
    assert code == 4401


def test_vehicle_send_refuses_a_bad_message():
    with pytest.raises(ProtocolError):
        vehicle_send(
            vehicle_id="00000000-0000-0000-0000-000000000001",
            message=Revoke(session_id="s", reason="r", action="explode"),  # type: ignore[arg-type]
        )
    with pytest.raises(ValueError):
        vehicle_send(vehicle_id="not-a-uuid", message=Task(token="t"))
    with pytest.raises(ValueError):  # not one of the messages owed until acknowledged
        vehicle_send(vehicle_id=SESSION, message=RelayClose(session_id="s", conn="c"))  # type: ignore[arg-type]


async def test_session_messages_are_handed_to_the_session_owner():
    vehicle, credential = await vehicle_enrolled()
    with hearing("agent_message") as said:
        comm, _ = await uplink_welcomed(vehicle, credential)
        sent = [
            {"type": "task_accepted", "session_id": "s-1"},
            {"type": "task_refused", "session_id": None, "code": "bad_signature", "reason": "x"},
            {"type": "event", "session_id": None, "event": "boot", "data": {"extra": 1}},
        ]
        for msg in sent:
            await comm.send_json_to(msg)
        await comm.send_to(text_data="sync")
        await comm.receive_json_from(timeout=5)
        # As structs, each as the agent said it.
        assert [(s["vehicle_id"], message_to_dict(s["message"])) for s in said] == [
            (str(vehicle.pk), msg) for msg in sent
        ]
        assert [type(s["message"]) for s in said] == [TaskAccepted, TaskRefused, Event]
        await comm.disconnect()


async def test_a_failing_listener_is_logged_and_does_not_break_the_uplink(caplog):
    vehicle, credential = await vehicle_enrolled()

    def broken(**kwargs):
        raise RuntimeError("bug in a listener")

    with hearing("agent_message", instead=broken) as said:
        comm, _ = await uplink_welcomed(vehicle, credential)
        await comm.send_json_to({"type": "task_accepted", "session_id": "s-1"})
        await comm.send_json_to({"type": "heartbeat", "seq": 1, "battery": 33})
        await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).battery == 33)
        assert await comm.receive_nothing(timeout=0.1)
        assert len(said) == 1
        # Logged where an operator looks, with where it failed.
        (failed,) = [r for r in caplog.records if r.name == "fleet.vehicle_events"]
        assert "task_accepted" in failed.getMessage()
        assert failed.exc_info is not None and "bug in a listener" in str(failed.exc_info[1])
        await comm.disconnect()


async def test_a_platform_failure_is_answered_and_the_uplink_stays(monkeypatch):
    vehicle, credential = await vehicle_enrolled()

    def broken(**kwargs):
        raise RuntimeError("database hiccup")

    monkeypatch.setattr(uplink, "vehicle_record_profile", broken)
    comm, _ = await uplink_welcomed(vehicle, credential)
    await comm.send_json_to(PROFILE)
    assert (await comm.receive_json_from(timeout=5))["code"] == "internal"
    await comm.send_json_to({"type": "heartbeat", "seq": 1, "battery": 21})
    await eventually(lambda: Vehicle.objects.get(pk=vehicle.pk).battery == 21)
    await comm.disconnect()


async def test_a_platform_failure_during_hello_closes_for_a_retry(monkeypatch):
    vehicle, credential = await vehicle_enrolled()

    def broken(**kwargs):
        raise RuntimeError("database down")

    monkeypatch.setattr(uplink, "vehicle_authenticate", broken)
    messages, code = await _hello_closed(vehicle, credential)
    assert code == 4500 and messages[0]["code"] == "internal"


# --- fuzz -------------------------------------------------------------------------------

_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=20),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=10), inner, max_size=4)
    ),
    max_leaves=12,
)
_fields = sorted(
    {"seq", "v", "vehicle_id", "credential", "session_id", "event", "data", "code", "reason"}
    | {"position", "battery", "status", "commands", "control_url", "payload", "conn"}
)
_messages = st.fixed_dictionaries(
    {"type": st.sampled_from([*sorted(MESSAGE_TYPES["uplink_to_platform"]), "nope"])},
    optional={name: _json for name in _fields},
)
_frames = st.one_of(
    st.text(max_size=200).map(lambda t: {"text_data": t}),
    _json.map(lambda v: {"text_data": json.dumps(v)}),
    _messages.map(lambda m: {"text_data": json.dumps(m)}),
    st.binary(max_size=100).map(lambda b: {"bytes_data": b}),
)


@pytest.fixture
async def fuzz_agent(monkeypatch):
    monkeypatch.setattr(uplink, "BAD_FRAMES_MAX", 10_000)  # the fuzzer is not a flood
    vehicle, credential = await vehicle_enrolled()
    comm, _ = await uplink_welcomed(vehicle, credential)
    yield comm
    await comm.disconnect()


_probe = iter(range(10**9))


@given(frame=_frames)
@hsettings(
    max_examples=50,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
async def test_fuzzed_frames_are_answered_or_accepted_never_crash(fuzz_agent, frame):
    comm = fuzz_agent
    # send_input rather than send_to, which refuses empty frames.
    if "text_data" in frame:
        await comm.send_input({"type": "websocket.receive", "text": frame["text_data"]})
    else:
        await comm.send_input({"type": "websocket.receive", "bytes": frame["bytes_data"]})
    # A probe the consumer must answer after handling the fuzzed frame (frames are
    # handled in order): everything before its answer came from the fuzzed frame.
    probe = f"probe-{next(_probe)}"
    await comm.send_json_to({"type": probe})
    replies = []
    while True:
        out = await comm.receive_output(timeout=5)
        assert out["type"] == "websocket.send", f"uplink closed on {frame!r}: {out}"
        reply = json.loads(out["text"])
        if probe in reply.get("message", ""):
            break
        replies.append(reply)
    assert len(replies) <= 1
    for reply in replies:
        assert reply["type"] == "error" and reply["code"] != "internal", reply


async def test_a_hello_that_waited_too_long_for_the_database_is_turned_away(monkeypatch):
    # A platform restart brings thousands of hellos at once; one that queued for a
    # database thread longer than its agent waits for the welcome is turned away at
    # once (4503, "busy") instead of admitted for nobody, and nothing is written.
    from fleet import uplink

    monkeypatch.setattr(uplink, "ADMIT_WITHIN_S", -1.0)  # every hello has waited too long
    vehicle, credential = await vehicle_enrolled()
    messages, code = await _hello_closed(vehicle, credential)
    assert code == 4503
    assert [m["code"] for m in messages] == ["busy"]
    assert (await _get(vehicle)).last_seen is None


def test_every_close_code_is_one_daphne_can_send():
    # daphne's WebSocket server (autobahn) refuses to close with any code but 1000 or
    # 3000-4999: a refusal with another one raised instead of closing the socket.
    from fleet import uplink

    codes = {name: value for name, value in vars(uplink).items() if name.startswith("CLOSE_")}
    assert len(codes) >= 7, codes
    assert all(code == 1000 or 3000 <= code <= 4999 for code in codes.values()), codes
