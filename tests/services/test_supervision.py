"""Supervision: what agents report on the uplink, and the rules applied to it.

Most tests tell the supervisor agent messages exactly as the uplink does
(``fleet.vehicle_events`` with a message from ``parse_message``); the last one drives
the whole flow through a real uplink socket.
"""

from __future__ import annotations

import asyncio
import json
import uuid
from datetime import UTC, datetime, timedelta

import pytest
import time_machine
from channels.db import database_sync_to_async
from django.conf import settings
from django.db import connections
from django.utils import timezone

from agents.protocol import VehicleTask, parse_message
from agents.protocol.messages import Heartbeat
from fleet.models import Vehicle
from fleet.status import vehicles_mark_stale_offline
from fleet.uplink import HeartbeatReport, vehicle_record_heartbeats
from fleet.vehicle_events import vehicle_events
from services.models import Session, SessionEvent
from services.sessions.ending import session_end
from services.sessions.log import session_log_verify
from services.sessions.opening import session_open
from services.sessions.signing import platform_public_key
from services.supervision.reports import LINK_QUALITY_EVERY_S
from services.supervision.timers import (
    sessions_end_vehicle_lost,
    sessions_expire_grace,
    sessions_expire_time_limit,
    sessions_expire_unconnected,
    sessions_expire_undelivered,
)
from tests import factories as f
from tests.deployment import session_requested
from tests.uplink import uplink_welcomed, vehicle_enrolled

pytestmark = pytest.mark.django_db


@pytest.fixture
def live(inbox, committing):
    """(session, vehicle, take) for a deployed session of a service that lands on
    fail-safe, with the vehicle's agent messages readable through ``take``."""
    vehicle = f.vehicle(station=f.station(), vtype=f.vehicle_type())
    take = inbox(vehicle)
    service = f.service(allowed_commands=["up"], failsafe_action="land")
    with committing():
        session = session_requested(user=f.user(username="alice"), service=service).session
    assert take()[0]["type"] == "task"
    return session, vehicle, take


def say(vehicle, msg):
    """Tell the supervisor ``msg`` from ``vehicle``'s agent as the uplink does (but with
    its exceptions raised)."""
    message = parse_message(json.dumps(msg), channel="uplink_to_platform")
    vehicle_events().agent_message(vehicle_id=str(vehicle.pk), message=message)


#: What an agent that runs nothing and says no status reports as it registers.
NOTHING_SAID = {"session_id": None, "controller": False, "status": None}


def event(session, which, /, **data):
    return {"type": "event", "session_id": str(session.pk), "event": which, "data": data}


def kinds(session):
    return list(session.events.order_by("seq").values_list("kind", flat=True))


def state(session):
    session.refresh_from_db()
    return session.state


def status(vehicle):
    return Vehicle.objects.get(pk=vehicle.pk).status


# --- tasks ------------------------------------------------------------------------------


def test_task_accepted_is_logged(live):
    session, vehicle, _ = live
    say(vehicle, {"type": "task_accepted", "session_id": str(session.pk)})
    assert session.events.get(kind="task_accepted").data == {"vehicle": str(vehicle.pk)}


def test_task_refused_fails_the_session_with_the_agents_reason(live, committing):
    session, vehicle, take = live
    with committing():
        say(
            vehicle,
            {
                "type": "task_refused",
                "session_id": str(session.pk),
                "code": "expired",
                "reason": "task arrived after its deadline",
            },
        )
    assert state(session) == Session.State.FAILED
    assert "task arrived after its deadline (expired)" in session.reason
    (end,) = take()
    assert end["type"] == "end_task"
    assert status(vehicle) == Vehicle.Status.RELEASING
    take.ack(end)
    assert status(vehicle) == Vehicle.Status.IDLE


def test_late_task_accepted_for_an_ended_session_is_told_to_end(live, committing):
    session, vehicle, take = live
    with committing():
        session_end(session=session, reason="user left", by_user=True)
    end = {"type": "end_task", "session_id": str(session.pk), "reason": "user left"}
    assert take() == [end]
    # The end is still owed: a late acceptance does not owe it twice.
    with committing():
        say(vehicle, {"type": "task_accepted", "session_id": str(session.pk)})
    assert [m.kind for m in take.owed()] == ["end_task"]
    # Once the agent has confirmed an end, a later acceptance is told again.
    take.ack(end)
    with committing():
        say(vehicle, {"type": "task_accepted", "session_id": str(session.pk)})
    assert take() == [end]


def test_a_task_never_accepted_fails_the_session_after_its_deadline(live):
    session, vehicle, _ = live
    deadline = session.events.get(kind="task_deployed").data["exp"]
    at = datetime.fromtimestamp(deadline, tz=UTC)
    assert sessions_expire_undelivered(now=at) == []  # not late yet
    # The agent could not read it and refused with a null session id: nobody can tell.
    say(
        vehicle, {"type": "task_refused", "session_id": None, "code": "bad_signature", "reason": ""}
    )
    assert sessions_expire_undelivered(now=at + timedelta(seconds=5)) == [str(session.pk)]
    assert state(session) == Session.State.FAILED
    assert session.reason == f"vehicle {vehicle.name} did not accept its task in time"
    # The task was sent: the agent may hold it, so it is told to end it first.
    assert status(vehicle) == Vehicle.Status.RELEASING


def test_an_accepted_task_is_not_undelivered(live):
    session, vehicle, _ = live
    say(vehicle, {"type": "task_accepted", "session_id": str(session.pk)})
    later = timezone.now() + timedelta(days=1)
    assert sessions_expire_undelivered(now=later) == []
    assert state(session) == Session.State.ASSIGNED


# --- users ------------------------------------------------------------------------------


def test_user_connected_activates_the_session(live):
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", user="alice", role="controller"))
    assert state(session) == Session.State.ACTIVE and session.started_at
    assert status(vehicle) == Vehicle.Status.IN_SERVICE
    assert session.events.get(kind="user_connected").data["user"] == "alice"
    say(vehicle, event(session, "user_disconnected", user="alice"))
    assert kinds(session)[-1] == "user_disconnected"


def test_a_viewer_connecting_does_not_activate(live):
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", user="bob", role="viewer"))
    assert state(session) == Session.State.ASSIGNED
    assert "user_connected" in kinds(session)


# --- unsafe behaviour -------------------------------------------------------------------


def test_repeated_unsafe_refusals_revoke(live, committing):
    session, vehicle, take = live
    say(vehicle, event(session, "user_connected", role="controller"))
    # Refused, but not unsafe: a round trip over the limit is the link's doing.
    for code in ["not_allowed", "bad_args", "latency"] * 3:
        say(vehicle, event(session, "command_refused", name="up", code=code))
    for code in ["altitude_limit", "geofence", "unsafe", "obstacle", "geofence"]:
        say(vehicle, event(session, "command_refused", name="up", code=code))
    assert state(session) == Session.State.ACTIVE  # five is the most tolerated
    with committing():
        say(vehicle, event(session, "command_refused", name="up", code="altitude_limit"))
    assert state(session) == Session.State.ABORTED
    assert session.reason == "repeated unsafe commands"
    assert take() == [
        {
            "type": "revoke",
            "session_id": str(session.pk),
            "reason": "repeated unsafe commands",
            "action": "land",
        }
    ]


def test_unsafe_refusals_spread_out_are_tolerated(live):
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", role="controller"))
    start = timezone.now()
    window = settings.IOUV_UNSAFE_REFUSALS_WINDOW_S
    for i in range(12):
        with time_machine.travel(start + timedelta(seconds=i * window / 4), tick=False):
            say(vehicle, event(session, "command_refused", name="up", code="geofence"))
    assert state(session) == Session.State.ACTIVE


# --- fail-safe and the reconnection grace -----------------------------------------------


def test_failsafe_logs_an_unintentional_end_then_the_grace_ends_the_session(live, committing):
    session, vehicle, take = live
    say(vehicle, event(session, "user_connected", role="controller"))
    say(vehicle, event(session, "failsafe", cause="link_lost", action="land"))
    logged = session.events.get(kind="unintentional_end")
    assert logged.data == {"vehicle": str(vehicle.pk), "cause": "link_lost", "action": "land"}
    assert status(vehicle) == Vehicle.Status.FAILSAFE
    assert state(session) == Session.State.ACTIVE

    grace = settings.IOUV_RECONNECT_GRACE_S
    assert sessions_expire_grace(now=logged.created_at + timedelta(seconds=grace - 1)) == []
    with committing():
        ended = sessions_expire_grace(now=logged.created_at + timedelta(seconds=grace + 1))
    assert ended == [str(session.pk)]
    assert state(session) == Session.State.ENDED
    # In words, not codes: what happened, what the vehicle did, and why it ended.
    assert session.reason == (
        f"the driver's link to the vehicle was lost, so {vehicle.name} will land; "
        f"nobody took control again within {grace:g} s"
    )
    (end,) = take()
    assert end["type"] == "end_task"
    take.ack(end)
    assert status(vehicle) == Vehicle.Status.IDLE
    assert sessions_expire_grace(now=logged.created_at + timedelta(seconds=grace + 99)) == []


def test_reconnecting_within_the_grace_keeps_the_session(live):
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", role="controller"))
    say(vehicle, event(session, "failsafe", cause="link_lost", action="land"))
    say(vehicle, event(session, "user_connected", role="controller"))
    later = timezone.now() + timedelta(seconds=settings.IOUV_RECONNECT_GRACE_S + 60)
    assert sessions_expire_grace(now=later) == []
    assert state(session) == Session.State.ACTIVE
    assert status(vehicle) == Vehicle.Status.IN_SERVICE


def test_a_viewer_reconnecting_does_not_stop_the_grace(live):
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", role="controller"))
    say(vehicle, event(session, "failsafe", cause="link_lost", action="stop"))
    say(vehicle, event(session, "user_connected", role="viewer"))
    later = timezone.now() + timedelta(seconds=settings.IOUV_RECONNECT_GRACE_S + 1)
    assert sessions_expire_grace(now=later) == [str(session.pk)]


# --- time limit -------------------------------------------------------------------------


def test_time_limit_revokes(inbox, committing):
    vehicle = f.vehicle(station=f.station(), vtype=f.vehicle_type())
    take = inbox(vehicle)
    service = f.service(session_time_limit_s=60, failsafe_action="return_to_home")
    with committing():
        session = session_requested(user=f.user(), service=service).session
    take()
    say(vehicle, event(session, "user_connected", role="controller"))
    started = Session.objects.get(pk=session.pk).started_at
    assert sessions_expire_time_limit(now=started + timedelta(seconds=59)) == []
    with committing():
        revoked = sessions_expire_time_limit(now=started + timedelta(seconds=61))
    assert revoked == [str(session.pk)]
    assert state(session) == Session.State.ABORTED and session.reason == "time limit reached"
    assert take()[0] == {
        "type": "revoke",
        "session_id": str(session.pk),
        "reason": "time limit reached",
        "action": "return_to_home",
    }


def test_sessions_without_a_time_limit_run_on(live):
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", role="controller"))
    assert sessions_expire_time_limit(now=timezone.now() + timedelta(days=1)) == []


# --- who may report what ----------------------------------------------------------------


def test_reports_on_other_sessions_are_ignored(live, caplog):
    session, vehicle, _ = live
    stranger = f.vehicle(station=f.station(), vtype=f.vehicle_type())
    before = kinds(session)
    say(stranger, event(session, "user_connected", role="controller"))
    say(stranger, event(session, "failsafe", cause="link_lost", action="land"))
    say(
        stranger,
        {"type": "task_refused", "session_id": str(session.pk), "code": "busy", "reason": ""},
    )
    assert kinds(session) == before and state(session) == Session.State.ASSIGNED
    assert status(stranger) == Vehicle.Status.IDLE
    assert "not assigned to" in caplog.text

    say(
        vehicle,
        event(session, "user_connected", role="controller") | {"session_id": str(uuid.uuid4())},
    )
    say(vehicle, event(session, "user_connected") | {"session_id": "not-a-uuid"})
    say(vehicle, {"type": "event", "session_id": None, "event": "boot", "data": {}})
    say(vehicle, {"type": "task_refused", "code": "bad_token", "reason": "unreadable"})
    assert kinds(session) == before and state(session) == Session.State.ASSIGNED
    assert "unknown session" in caplog.text


def test_link_quality_is_sampled(live):
    session, vehicle, _ = live
    start = timezone.now()
    for offset in (0, 1, 5, LINK_QUALITY_EVERY_S + 1):
        with time_machine.travel(start + timedelta(seconds=offset), tick=False):
            say(vehicle, event(session, "link_quality", rtt_ms=100 + offset))
    logged = session.events.filter(kind="link_quality").order_by("seq")
    assert [e.data["rtt_ms"] for e in logged] == [100, 100 + LINK_QUALITY_EVERY_S + 1]


def test_other_events_are_logged(live):
    session, vehicle, _ = live
    say(vehicle, event(session, "task_ended", reason="revoked"))
    say(vehicle, event(session, "speed_limited", factor=0.5))
    assert kinds(session)[-2:] == ["task_ended", "agent_event"]
    assert session.events.last().data == {
        "vehicle": str(vehicle.pk),
        "event": "speed_limited",
        "data": {"factor": 0.5},
    }


def test_an_event_is_logged_with_the_time_it_happened_on_the_vehicle(live):
    """A report that waited (the platform or its database away) is written late: the
    log keeps when it happened, by the vehicle's clock, beside when it was written."""
    session, vehicle, _ = live
    happened = datetime(2026, 5, 4, 10, 21, 7, 500_000, tzinfo=UTC)
    with time_machine.travel(happened + timedelta(seconds=12), tick=False):
        say(vehicle, {**event(session, "speed_limited", factor=0.5), "at": happened.timestamp()})
        say(vehicle, event(session, "user_connected", user="alice", role="controller"))
    logged, connected, activated = session.events.order_by("-seq")[:3][::-1]
    assert (logged.kind, logged.occurred_at) == ("agent_event", happened)
    assert logged.created_at == happened + timedelta(seconds=12)
    # An older agent says nothing of the time: nothing is made up.
    assert (connected.kind, connected.occurred_at) == ("user_connected", None)
    assert activated.kind == "state" and activated.occurred_at is None
    # The vehicle's time is part of what the chain covers.
    assert session_log_verify(session=session).ok
    SessionEvent.objects.filter(pk=logged.pk).update(occurred_at=happened + timedelta(seconds=1))
    check = session_log_verify(session=session)
    assert not check.ok and check.bad_seq == logged.seq


# --- agents coming and going ------------------------------------------------------------


def test_uplink_loss_and_return_during_a_session(live, committing):
    session, vehicle, take = live
    say(vehicle, event(session, "user_connected", role="controller"))
    Vehicle.objects.filter(pk=vehicle.pk).update(status=Vehicle.Status.OFFLINE)
    vehicle_events().agent_disconnected(vehicle_id=str(vehicle.pk), code=1006)
    assert session.events.last().kind == "vehicle_offline"

    # Back: the uplink's profile made it idle; supervision puts it back in service and
    # sends a fresh task (new nonce), since a restarted agent lost the old one.
    Vehicle.objects.filter(pk=vehicle.pk).update(status=Vehicle.Status.IDLE)
    with committing():
        vehicle_events().agent_connected(vehicle_id=str(vehicle.pk), state=NOTHING_SAID)
    assert "vehicle_online" in kinds(session)
    assert status(vehicle) == Vehicle.Status.IN_SERVICE
    (message,) = take()
    task = VehicleTask.verify(message["token"], platform_public_key(), vehicle_id=str(vehicle.pk))
    nonces = [e.data["nonce"] for e in session.events.filter(kind="task_deployed")]
    assert len(nonces) == 2 and task.nonce == nonces[-1] != nonces[0]


def test_an_agent_back_in_fail_safe_with_its_session_gets_the_sessions_status(live):
    """A platform process restarted: the agent reconnects and says it is in fail-safe
    (its relayed user was cut off with the process). Its session still holds it: the
    user comes back and drives on, and nobody else may have it meanwhile."""
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", role="controller"))
    # What the uplink's profile made of the report "failsafe" (fleet.uplink).
    Vehicle.objects.filter(pk=vehicle.pk).update(status=Vehicle.Status.FAILSAFE)
    vehicle_events().agent_connected(
        vehicle_id=str(vehicle.pk),
        state={"session_id": str(session.pk), "controller": False, "status": "failsafe"},
    )
    assert status(vehicle) == Vehicle.Status.IN_SERVICE
    assert state(session) == Session.State.ACTIVE


def test_an_idle_vehicle_coming_online_is_left_alone():
    vehicle = f.vehicle(station=f.station(), vtype=f.vehicle_type())
    vehicle_events().agent_connected(vehicle_id=str(vehicle.pk), state=NOTHING_SAID)
    vehicle_events().agent_disconnected(vehicle_id=str(vehicle.pk), code=1000)
    assert status(vehicle) == Vehicle.Status.IDLE


# --- sessions follow what really happens -------------------------------------------------


def _past_grace(event_kind, session):
    logged = session.events.filter(kind=event_kind).last()
    return logged.created_at + timedelta(seconds=settings.IOUV_RECONNECT_GRACE_S + 1)


def test_input_again_on_the_open_socket_keeps_the_session(live):
    """A throttled tab stalls, the fail-safe acts, the user drives on: that is recovery."""
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", role="controller"))
    say(vehicle, event(session, "failsafe", cause="link_lost", action="land"))
    assert status(vehicle) == Vehicle.Status.FAILSAFE
    say(vehicle, event(session, "link_recovered", user="alice", after_ms=900))
    assert status(vehicle) == Vehicle.Status.IN_SERVICE
    assert sessions_expire_grace(now=_past_grace("unintentional_end", session)) == []
    assert state(session) == Session.State.ACTIVE


def test_the_session_keeps_the_path_its_controller_drives_on(live):
    """The agent says how each user's messages travel (WebRTC direct or through TURN,
    the relay, the direct socket); the session keeps the controller's, the log all."""
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", role="controller"))
    say(vehicle, event(session, "control_path", user="alice", role="controller", path="relay"))
    say(
        vehicle, event(session, "control_path", user="alice", role="controller", path="webrtc_turn")
    )
    say(vehicle, event(session, "control_path", user="bob", role="viewer", path="webrtc_direct"))
    say(
        vehicle,
        event(session, "control_path", user="alice", role="controller", path="carrier-pigeon"),
    )
    session.refresh_from_db()
    assert session.control_path == "webrtc_turn"
    paths = [e.data["path"] for e in session.events.filter(kind="control_path").order_by("seq")]
    assert paths == ["relay", "webrtc_turn", "webrtc_direct"]  # the unknown one is dropped


def test_the_controller_leaving_ends_the_session_after_the_grace(live, committing):
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", user="alice", role="controller"))
    say(vehicle, event(session, "user_disconnected", user="alice", role="controller"))
    say(vehicle, event(session, "user_connected", user="bob", role="viewer"))
    with committing():
        assert sessions_expire_grace(now=_past_grace("user_disconnected", session)) == [
            str(session.pk)
        ]
    grace = settings.IOUV_RECONNECT_GRACE_S
    assert state(session) == Session.State.ENDED
    assert session.reason == f"the user left and did not come back within {grace:g} s"


def test_control_taken_up_again_from_another_tab_keeps_the_session(live):
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", user="alice", role="controller"))
    say(vehicle, event(session, "user_disconnected", user="alice", role="controller"))
    say(vehicle, event(session, "control_handover", user="alice", role="controller"))
    assert sessions_expire_grace(now=_past_grace("user_disconnected", session)) == []
    assert kinds(session)[-1] == "control_handover"


def test_control_put_down_and_not_taken_back_ends_the_session(live, committing):
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", user="alice", role="controller"))
    say(vehicle, event(session, "control_released", user="alice", role="controller"))
    with committing():
        assert sessions_expire_grace(now=_past_grace("control_released", session)) == [
            str(session.pk)
        ]
    assert state(session) == Session.State.ENDED
    assert "released control" in session.reason


def test_a_vehicle_back_online_with_its_controller_keeps_the_session(live):
    """The uplink dropped, not the user: the agent says its controller is still there."""
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", role="controller"))
    say(vehicle, event(session, "failsafe", cause="link_lost", action="land"))
    vehicle_events().agent_connected(
        vehicle_id=str(vehicle.pk),
        state={"session_id": str(session.pk), "controller": True, "status": "in_service"},
    )
    assert sessions_expire_grace(now=_past_grace("unintentional_end", session)) == []


def test_a_session_nobody_connects_to_ends_after_the_connect_timeout(live, committing):
    session, _vehicle, _ = live
    assigned = Session.objects.get(pk=session.pk).assigned_at
    limit = settings.IOUV_CONNECT_TIMEOUT_S
    assert sessions_expire_unconnected(now=assigned + timedelta(seconds=limit - 1)) == []
    with committing():
        ended = sessions_expire_unconnected(now=assigned + timedelta(seconds=limit + 1))
    assert ended == [str(session.pk)]
    assert state(session) == Session.State.ENDED
    assert session.reason == f"nobody connected to the vehicle within {limit:g} s"


def test_an_autonomous_session_waits_for_no_user(inbox, committing):
    vehicle = f.vehicle(station=f.station(), vtype=f.vehicle_type())
    service = f.service(kind="rescue_at_sea")
    # Its vehicle reserved and its task sent at once, as a workflow's step would.
    session_open(user=f.user(), service=service, deploy=True)
    later = timezone.now() + timedelta(seconds=settings.IOUV_CONNECT_TIMEOUT_S + 60)
    assert sessions_expire_unconnected(now=later) == []
    assert status(vehicle) == Vehicle.Status.RESERVED


def test_a_session_whose_vehicle_went_offline_ends_and_the_vehicle_stays_held(live, committing):
    session, vehicle, take = live
    say(vehicle, event(session, "user_connected", role="controller"))
    seen = timezone.now()
    Vehicle.objects.filter(pk=vehicle.pk).update(status=Vehicle.Status.OFFLINE, last_seen=seen)
    lost = settings.IOUV_VEHICLE_LOST_S
    assert sessions_end_vehicle_lost(now=seen + timedelta(seconds=lost - 0.5)) == []
    with committing():
        assert sessions_end_vehicle_lost(now=seen + timedelta(seconds=lost + 0.5)) == [
            str(session.pk)
        ]
    assert state(session) == Session.State.ENDED
    assert session.reason == f"vehicle {vehicle.name} went offline (no word from it for {lost:g} s)"
    # Not freed: nobody knows where it is. It is told the session is over when back.
    assert status(vehicle) == Vehicle.Status.OFFLINE
    assert [m.kind for m in take.owed()] == ["end_task"]


def test_an_agent_back_with_a_session_that_ended_is_told_to_end_it(live, committing):
    session, vehicle, take = live
    say(vehicle, event(session, "user_connected", role="controller"))
    Vehicle.objects.filter(pk=vehicle.pk).update(status=Vehicle.Status.OFFLINE)
    with committing():
        session_end(session=session, reason="vehicle lost", by_user=False)
    # Its uplink comes back; the profile says it still runs the session.
    Vehicle.objects.filter(pk=vehicle.pk).update(status=Vehicle.Status.RELEASING)
    with committing():
        vehicle_events().agent_connected(
            vehicle_id=str(vehicle.pk),
            state={"session_id": str(session.pk), "controller": True, "status": "in_service"},
        )
    end = {"type": "end_task", "session_id": str(session.pk), "reason": "vehicle lost"}
    assert take() == [end]  # once, though decided before and again now
    assert status(vehicle) == Vehicle.Status.RELEASING
    take.ack(end)
    assert status(vehicle) == Vehicle.Status.IDLE


def test_a_restarted_agent_gets_its_live_session_back_and_nothing_stale(live, committing):
    session, vehicle, take = live
    Vehicle.objects.filter(pk=vehicle.pk).update(status=Vehicle.Status.IDLE)
    with committing():
        vehicle_events().agent_connected(
            vehicle_id=str(vehicle.pk),
            state={"session_id": None, "controller": False, "status": "idle"},
        )
    (message,) = take()
    assert message["type"] == "task"  # a fresh one: the first may have expired
    assert status(vehicle) == Vehicle.Status.RESERVED
    assert kinds(session).count("task_deployed") == 2


def test_a_restarted_agent_owes_nothing_for_sessions_it_no_longer_runs(live, committing):
    session, vehicle, take = live
    with committing():
        session_end(session=session, reason="done", by_user=True)
    assert status(vehicle) == Vehicle.Status.RELEASING
    # It restarted before the end reached it: there is nothing left to end.
    Vehicle.objects.filter(pk=vehicle.pk).update(status=Vehicle.Status.IDLE)
    vehicle_events().agent_connected(
        vehicle_id=str(vehicle.pk),
        state={"session_id": None, "controller": False, "status": "idle"},
    )
    assert take.owed() == []
    assert status(vehicle) == Vehicle.Status.IDLE


def test_a_vehicle_found_silent_and_heard_again_keeps_its_session(live):
    """The sweep marked it offline (late heartbeats); a heartbeat on its open uplink
    must not make a vehicle in a session look free."""
    session, vehicle, _ = live
    say(vehicle, event(session, "user_connected", role="controller"))
    assert vehicles_mark_stale_offline(now=timezone.now() + timedelta(seconds=60)) == [vehicle.pk]
    assert status(vehicle) == Vehicle.Status.OFFLINE
    beat = Heartbeat(seq=9, status="in_service")
    vehicle_record_heartbeats([HeartbeatReport(str(vehicle.pk), beat, timezone.now(), True)])
    assert status(vehicle) == Vehicle.Status.IN_SERVICE
    assert kinds(session)[-1] == "vehicle_online"


def test_refusals_reported_in_aggregate_count_each_refusal(live, committing):
    session, vehicle, _take = live
    say(vehicle, event(session, "user_connected", role="controller"))
    say(vehicle, event(session, "command_refused", name="up", code="altitude_limit", count=1))
    say(
        vehicle,
        event(
            session,
            "command_refused",
            name="up",
            code="altitude_limit",
            count=40,
            codes={"not_allowed": 36, "altitude_limit": 4},
        ),
    )
    assert state(session) == Session.State.ACTIVE  # 5 unsafe of 41: the most tolerated
    with committing():
        say(vehicle, event(session, "command_refused", name="up", code="geofence", count=1))
    assert state(session) == Session.State.ABORTED
    assert session.reason == "repeated unsafe commands"


def test_reports_after_the_session_ended_are_not_logged(live, committing):
    session, vehicle, _ = live
    with committing():
        session_end(session=session, reason="done", by_user=True)
    before = kinds(session)
    say(vehicle, event(session, "command_refused", name="up", code="view_only", count=150))
    say(vehicle, event(session, "link_quality", rtt_ms=20))
    say(vehicle, event(session, "task_ended", reason="done"))
    assert kinds(session) == [*before, "task_ended"]


# --- the whole flow over a real uplink --------------------------------------------------


@pytest.fixture
async def _close_worker_connections():
    yield
    await database_sync_to_async(connections.close_all)()


@pytest.mark.django_db(transaction=True)
async def test_agent_flow_over_the_uplink(_close_worker_connections):
    vehicle, credential = await vehicle_enrolled()
    agent, _ = await uplink_welcomed(vehicle, credential)
    await agent.send_json_to(
        {
            "type": "profile",
            "vehicle_type": "drone",
            "adapter": "sim",
            "attributes": {},
            "commands": [{"name": "up", "args": {}}],
            "telemetry": ["battery"],
            "control_url": "ws://127.0.0.1:9000/",
            "video": False,
            "position": None,
            "battery": 95,
        }
    )
    for _ in range(250):
        if await database_sync_to_async(status)(vehicle) == Vehicle.Status.IDLE:
            break
        await asyncio.sleep(0.02)

    @database_sync_to_async
    def request():
        service = f.service(allowed_commands=["up"])
        opened = session_requested(user=f.user(username="carol"), service=service)
        return opened.session, opened.task

    session, user_task = await request()
    assert user_task.control_url == "ws://127.0.0.1:9000/"
    message = await agent.receive_json_from(timeout=5)
    task = VehicleTask.verify(message["token"], platform_public_key(), vehicle_id=str(vehicle.pk))
    assert task.session_id == str(session.pk) and task.user == "carol"

    await agent.send_json_to({"type": "task_accepted", "session_id": str(session.pk)})
    await agent.send_json_to(event(session, "user_connected", user="carol", role="controller"))
    for _ in range(250):
        if await database_sync_to_async(state)(session) == Session.State.ACTIVE:
            break
        await asyncio.sleep(0.02)
    assert await database_sync_to_async(status)(vehicle) == Vehicle.Status.IN_SERVICE

    await agent.send_json_to({"type": "ack", "id": message["id"], "ok": True})

    await database_sync_to_async(session_end)(session=session, reason="user left", by_user=True)
    end = await agent.receive_json_from(timeout=5)
    assert end == {
        "type": "end_task",
        "session_id": str(session.pk),
        "reason": "user left",
        "id": end["id"],
    }
    assert await database_sync_to_async(status)(vehicle) == Vehicle.Status.RELEASING
    await agent.send_json_to(event(session, "task_ended"))
    await agent.send_json_to({"type": "ack", "id": end["id"], "ok": True})
    for _ in range(250):
        if await database_sync_to_async(status)(vehicle) == Vehicle.Status.IDLE:
            break
        await asyncio.sleep(0.02)
    assert await database_sync_to_async(status)(vehicle) == Vehicle.Status.IDLE
    await agent.disconnect()
    for _ in range(250):
        if await database_sync_to_async(status)(vehicle) == Vehicle.Status.OFFLINE:
            break
        await asyncio.sleep(0.02)
    logged = await database_sync_to_async(kinds)(session)
    assert "task_accepted" in logged and logged[-2:] == ["task_ended", "end_delivered"]
    assert await database_sync_to_async(status)(vehicle) == Vehicle.Status.OFFLINE
