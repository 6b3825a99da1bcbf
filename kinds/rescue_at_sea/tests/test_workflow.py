"""The rescue workflow's state machine, step by step, against the demo's sea fleet.

Agents are played by publishing their reports exactly as the uplink does; each step is
run directly (in production Celery runs it), so every test can also run it twice and
check that nothing happens twice.
"""

from __future__ import annotations

import http.server
import json
import threading
from datetime import timedelta
from typing import Any

import pytest
import time_machine
from django.core import mail
from django.utils import timezone

from agents.geo import offset
from agents.missions.spec import MissionSpec
from agents.protocol import parse_message
from fleet.models import Vehicle
from fleet.vehicle_events import vehicle_events
from kinds.rescue_at_sea.conf import search_timeout_s
from kinds.rescue_at_sea.missions import vehicle_mission
from kinds.rescue_at_sea.models import Mission, RescueTeam
from kinds.rescue_at_sea.notifications import notices_create
from kinds.rescue_at_sea.presentation import mission_json
from kinds.rescue_at_sea.request import RescueError, rescue_request
from kinds.rescue_at_sea.tests.sea import SEA, area, online
from kinds.rescue_at_sea.workflow import mission_advance, missions_tick
from services.models import Assignment, Notice, Service, Session
from services.sessions.matching import AssignmentError
from services.sessions.notices import notices_send as notifications_send
from tests import factories as f

pytestmark = pytest.mark.django_db


def wire(spec: MissionSpec | None) -> dict[str, Any]:
    """The mission as it travels in the signed task (the JSON the agent decodes)."""
    assert spec is not None
    return spec.to_payload()


def say(vehicle: Vehicle, msg: dict) -> None:
    message = parse_message(json.dumps(msg), channel="uplink_to_platform")
    vehicle_events().agent_message(vehicle_id=str(vehicle.pk), message=message)


def report(session: Session, vehicle: Vehicle, name: str, **data) -> None:
    say(vehicle, {"type": "event", "session_id": str(session.pk), "event": name, "data": data})


def kinds(session: Session) -> list[str]:
    return list(session.events.order_by("seq").values_list("kind", flat=True))


def team_notices(session: Session) -> int:
    """Notices sent about the person found (dashboard, e-mail, webhook)."""
    return session.events.filter(kind="notice_sent", data__topic="person_in_water").count()


def mission(session: Session) -> Mission:
    return Mission.objects.get(pk=session.pk)


def step(session: Session) -> str | None:
    """One step, then the notice task it scheduled, as a worker runs both."""
    state = mission_advance(session.pk)
    notifications_send(session.pk)
    return state


@pytest.fixture
def client_user():
    return f.user(username="skipper")


def vehicle(name: str) -> Vehicle:
    return Vehicle.objects.get(name=name)


def test_whole_rescue_from_area_to_completed(world, client_user) -> None:
    session = rescue_request(user=client_user, service=world, area=area())
    m = mission(session)
    assert m.state == Mission.State.WAITING_SEARCH
    assert len(m.path) >= 4 and m.spacing_m == pytest.approx(34.8, abs=0.5)

    # The fastest thermal drone is assigned and gets the search pattern to fly.
    assert step(session) == Mission.State.SEARCHING
    search = Assignment.objects.get(session=session, role="search")
    assert search.vehicle.name == "search-1"
    m = mission(session)
    doc = wire(vehicle_mission(assignment=search))
    assert doc["kind"] == "search" and doc["start_index"] == 0 and doc["waypoints"] == m.path
    # The first waypoint is the end of the pattern nearest the drone's station.
    station = (search.vehicle.station.lat, search.vehicle.station.lon)
    from agents.geo import distance_m

    assert distance_m(station, tuple(m.path[0])) <= distance_m(station, tuple(m.path[-1]))
    session.refresh_from_db()
    assert session.state == Session.State.ASSIGNED
    say(search.vehicle, {"type": "task_accepted", "session_id": str(session.pk)})
    session.refresh_from_db()
    assert session.state == Session.State.ACTIVE

    report(
        session,
        search.vehicle,
        "mission_progress",
        mission=doc["id"],
        phase="search",
        waypoint=2,
        of=len(m.path),
    )
    assert mission(session).progress == 2
    # Progress never goes backwards, and nonsense is not recorded.
    report(session, search.vehicle, "mission_progress", mission=doc["id"], waypoint=1)
    report(session, search.vehicle, "mission_progress", mission=doc["id"], waypoint=999)
    assert mission(session).progress == 2
    assert step(session) == Mission.State.SEARCHING  # nothing new: nothing changes

    person = offset(SEA, 120, 150)
    report(
        session,
        search.vehicle,
        "person_detected",
        mission=doc["id"],
        lat=person[0],
        lon=person[1],
        confidence=0.93,
        temperature_c=33.5,
        area_m2=0.3,
    )
    assert mission(session).detection["confidence"] == 0.93
    assert step(session) == Mission.State.DELIVERING
    delivery = Assignment.objects.get(session=session, role="delivery")
    assert delivery.vehicle.name == "lifeguard-1"
    doc = wire(vehicle_mission(assignment=delivery))
    assert doc["kind"] == "delivery" and doc["target"] == [person[0], person[1]]
    # The rescue team heard once, by e-mail and on the dashboard, with the position.
    assert len(mail.outbox) == 1
    assert f"{person[0]:.5f}" in mail.outbox[0].subject
    assert mail.outbox[0].to == ["lifeguards@costanova.example"]
    assert mail.outbox[0].extra_headers["Message-ID"].startswith("<iouv-person_in_water-")
    assert team_notices(session) == 2
    deployed = kinds(session).count("task_deployed")
    step(session)
    step(session)
    assert len(mail.outbox) == 1 and team_notices(session) == 2
    assert Assignment.objects.filter(session=session, role="delivery").count() == 1
    assert kinds(session).count("task_deployed") == deployed

    say(delivery.vehicle, {"type": "task_accepted", "session_id": str(session.pk)})
    report(
        session,
        delivery.vehicle,
        "payload_released",
        mission=doc["id"],
        lat=person[0],
        lon=person[1],
    )
    assert step(session) == Mission.State.RETURNING
    # Both vehicles are sent home with a task of their own, the session still open: its
    # user watches the way back.
    session.refresh_from_db()
    assert session.state == Session.State.ACTIVE
    for vehicle in (search, delivery):
        home = wire(vehicle_mission(assignment=Assignment.objects.get(pk=vehicle.pk)))
        assert home["kind"] == "return" and home["id"].endswith("-home")
    home_tasks = session.events.filter(kind="task_deployed").order_by("-seq")[:2]
    assert {e.data["vehicle"] for e in home_tasks} == {
        str(search.vehicle_id),
        str(delivery.vehicle_id),
    }
    # The mission completes, and the session ends, once they have landed there.
    Vehicle.objects.filter(pk=search.vehicle_id).update(alt=40)
    assert step(session) == Mission.State.RETURNING
    online("search-1", "lifeguard-1")
    assert step(session) == Mission.State.COMPLETED
    session.refresh_from_db()
    assert session.state == Session.State.ENDED and "mission completed" in session.reason
    final = session.events.filter(kind="mission_state").order_by("-seq").first()
    assert set(final.data["timeline"]) == {
        "requested",
        "person_detected",
        "payload_released",
        "completed",
    }
    data = mission_json(mission(session))
    assert data["final"] and data["detection"]["lat"] == person[0]
    assert {v["role"] for v in data["vehicles"]} == {"search", "delivery"}


def test_offline_search_drone_hands_its_remaining_lines_to_another(
    world, client_user, settings
) -> None:
    spare = Vehicle.objects.get(name="search-1")
    spare.pk, spare.name = None, "search-2"
    spare.save()
    online("search-2")
    session = rescue_request(user=client_user, service=world, area=area())
    step(session)
    first = Assignment.objects.get(session=session, role="search", active=True)
    report(session, first.vehicle, "mission_progress", waypoint=3)
    # Heard from recently: not replaced yet.
    Vehicle.objects.filter(pk=first.vehicle_id).update(status=Vehicle.Status.OFFLINE)
    assert step(session) == Mission.State.SEARCHING
    assert Assignment.objects.get(pk=first.pk).active
    # Silent for longer than the grace: its remaining lines go to the other drone.
    Vehicle.objects.filter(pk=first.vehicle_id).update(
        last_seen=timezone.now() - timedelta(seconds=settings.IOUV_MISSION_OFFLINE_GRACE_S + 1)
    )
    assert step(session) == Mission.State.SEARCHING
    assert not Assignment.objects.get(pk=first.pk).active
    second = Assignment.objects.get(session=session, role="search", active=True)
    assert second.vehicle_id != first.vehicle_id
    doc = wire(vehicle_mission(assignment=second))
    assert doc["start_index"] == 3 and doc["waypoints"] == mission(session).path
    released = session.events.get(kind="vehicle_released")
    assert "went offline" in released.data["reason"] and released.data["progress"] == 3


def test_low_battery_search_drone_is_replaced(world, client_user) -> None:
    spare = Vehicle.objects.get(name="search-1")
    spare.pk, spare.name = None, "search-2"
    spare.save()
    online("search-2")
    session = rescue_request(user=client_user, service=world, area=area())
    step(session)
    first = Assignment.objects.get(session=session, role="search", active=True)
    Vehicle.objects.filter(pk=first.vehicle_id).update(battery=12)
    step(session)
    assert "low on battery" in session.events.get(kind="vehicle_released").data["reason"]
    assert (
        Assignment.objects.filter(session=session, role="search", active=True)
        .exclude(vehicle_id=first.vehicle_id)
        .exists()
    )


def test_no_vehicle_the_mission_waits_and_says_so(world, client_user) -> None:
    Vehicle.objects.update(status=Vehicle.Status.OFFLINE)
    session = rescue_request(user=client_user, service=world, area=area())
    assert step(session) == Mission.State.WAITING_SEARCH
    assert "search-1 is offline: this request is next in line" in mission(session).status_text
    waits = kinds(session).count("mission_state")
    step(session)
    assert kinds(session).count("mission_state") == waits  # said once, not every tick
    online("search-1", "lifeguard-1")
    assert missions_tick() == 1
    assert mission(session).state == Mission.State.SEARCHING


def test_no_delivery_vehicle_waits_after_detection(world, client_user) -> None:
    session = rescue_request(user=client_user, service=world, area=area())
    step(session)
    search = Assignment.objects.get(session=session, role="search")
    Vehicle.objects.filter(name="lifeguard-1").update(status=Vehicle.Status.OFFLINE)
    person = offset(SEA, 50, 50)
    report(session, search.vehicle, "person_detected", lat=person[0], lon=person[1], confidence=0.9)
    assert step(session) == Mission.State.WAITING_DELIVERY
    assert "waiting for a delivery vehicle" in mission(session).status_text
    online("lifeguard-1")
    assert step(session) == Mission.State.DELIVERING


def _delivering(world, client_user) -> tuple[Session, Assignment]:
    session = rescue_request(user=client_user, service=world, area=area())
    step(session)
    search = Assignment.objects.get(session=session, role="search")
    person = offset(SEA, 50, 50)
    report(session, search.vehicle, "person_detected", lat=person[0], lon=person[1], confidence=0.9)
    assert step(session) == Mission.State.DELIVERING
    return session, Assignment.objects.get(session=session, role="delivery", active=True)


def test_a_delivery_the_autopilot_refused_is_logged_and_shown_as_flown_step_by_step(
    world, client_user
) -> None:
    """The delivery drone's autopilot refused its plan (agents/missions/kit.py): the log
    and the timeline say so; the delivery goes on."""
    session, delivery = _delivering(world, client_user)
    reason = "the autopilot refused the mission: MAV_MISSION_DENIED (another ground station)"
    report(session, delivery.vehicle, "native_mission_refused", mission="d", reason=reason)
    assert session.events.get(kind="native_mission_refused").data["reason"] == reason
    assert step(session) == Mission.State.DELIVERING
    shown = mission_json(mission(session))["timeline"]
    assert [e["data"]["reason"] for e in shown if e["kind"] == "native_mission_refused"] == [reason]


def test_late_heartbeats_on_a_loaded_platform_do_not_call_the_delivery_back(
    world, client_user, settings
) -> None:
    """Its uplink is open and it flies on: silence in the database alone is not trouble."""
    session, delivery = _delivering(world, client_user)
    Vehicle.objects.filter(pk=delivery.vehicle_id).update(
        last_seen=timezone.now() - timedelta(seconds=settings.IOUV_MISSION_OFFLINE_GRACE_S + 5)
    )
    assert step(session) == Mission.State.DELIVERING
    assert Assignment.objects.get(pk=delivery.pk).active


def test_a_delivery_vehicle_that_went_offline_flies_again_once_back(
    world, client_user, settings
) -> None:
    """The only life-jacket carrier drops off and comes back: the mission must not sit
    in waiting_delivery for ever (seen under load)."""
    session, delivery = _delivering(world, client_user)
    Vehicle.objects.filter(pk=delivery.vehicle_id).update(
        status=Vehicle.Status.OFFLINE,
        last_seen=timezone.now() - timedelta(seconds=settings.IOUV_MISSION_OFFLINE_GRACE_S + 1),
    )
    assert step(session) == Mission.State.WAITING_DELIVERY
    released = session.events.get(kind="vehicle_released")
    assert released.data["cause"] == "offline"
    online("lifeguard-1")
    assert step(session) == Mission.State.DELIVERING
    again = Assignment.objects.get(session=session, role="delivery", active=True)
    assert again.vehicle_id == delivery.vehicle_id


def test_a_delivery_vehicle_that_failed_is_not_asked_again(world, client_user) -> None:
    session, delivery = _delivering(world, client_user)
    report(session, delivery.vehicle, "mission_failed", reason="gripper jammed")
    assert step(session) == Mission.State.WAITING_DELIVERY
    online("lifeguard-1")
    assert step(session) == Mission.State.WAITING_DELIVERY
    assert (
        "could not go on: gripper jammed"
        in session.events.get(kind="vehicle_released").data["reason"]
    )


def test_search_times_out_and_everyone_is_told(world, client_user, settings) -> None:
    session = rescue_request(user=client_user, service=world, area=area())
    step(session)
    later = timezone.now() + timedelta(seconds=search_timeout_s() + 5)
    with time_machine.travel(later):
        online("search-1", "lifeguard-1")  # still heard from
        assert step(session) == Mission.State.TIMED_OUT
    session.refresh_from_db()
    assert session.state == Session.State.ENDED and "timed out" in session.reason
    assert not Assignment.objects.filter(session=session, active=True).exists()


def test_whole_area_searched_without_finding(world, client_user) -> None:
    session = rescue_request(user=client_user, service=world, area=area())
    step(session)
    search = Assignment.objects.get(session=session, role="search")
    report(session, search.vehicle, "search_complete", waypoint=len(mission(session).path) - 1)
    assert step(session) == Mission.State.NOT_FOUND
    session.refresh_from_db()
    assert session.state == Session.State.ENDED


def test_monitor_stop_aborts_the_mission(world, client_user) -> None:
    from services.sessions.ending import session_revoke

    session = rescue_request(user=client_user, service=world, area=area())
    step(session)
    session_revoke(session=session, reason="stopped by monitor", action="return_to_home")
    assert step(session) == Mission.State.ABORTED


def test_reports_from_strangers_and_nonsense_change_nothing(world, client_user) -> None:
    session = rescue_request(user=client_user, service=world, area=area())
    step(session)
    search = Assignment.objects.get(session=session, role="search")
    stranger = vehicle("lifeguard-1")
    report(session, stranger, "person_detected", lat=40.64, lon=-8.75, confidence=1.0)
    report(session, search.vehicle, "person_detected", lat="north", lon=-8.75, confidence=1.0)
    report(session, search.vehicle, "person_detected", lat=95.0, lon=-8.75)
    report(session, search.vehicle, "payload_released", lat=40.64, lon=-8.75)  # not its role
    m = mission(session)
    assert m.detection is None and m.released_at is None
    assert step(session) == Mission.State.SEARCHING


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"area": [[1, 2]]}, "at least 3"),
        ({"area": area(), "altitude_m": 5}, "altitude"),
        ({"area": area(), "altitude_m": 500}, "altitude"),
    ],
)
def test_bad_requests_are_refused_and_record_nothing(world, client_user, kwargs, message) -> None:
    with pytest.raises(RescueError, match=message):
        rescue_request(user=client_user, service=world, **kwargs)
    assert not Session.objects.exists()


def test_users_without_the_grant_and_other_services_are_refused(world) -> None:
    with pytest.raises(AssignmentError, match="may not use"):
        rescue_request(user=f.user(roles=()), service=world, area=area())
    with pytest.raises(RescueError, match="not a rescue service"):
        rescue_request(user=f.user(), service=Service.objects.get(slug="fly-drone"), area=area())
    assert not Session.objects.exists()


class _Hook(http.server.BaseHTTPRequestHandler):
    status = 200
    seen: list[tuple[str, dict]] = []

    def do_POST(self) -> None:
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        type(self).seen.append((self.headers["Idempotency-Key"], body))
        self.send_response(type(self).status)
        self.end_headers()

    def log_message(self, *args) -> None:
        pass


def test_webhook_is_retried_until_it_succeeds_and_sent_once(world, client_user) -> None:
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Hook)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    _Hook.seen, _Hook.status = [], 503
    try:
        RescueTeam.objects.filter(station__name="Costa Nova station").update(
            webhook=f"http://127.0.0.1:{server.server_port}/alerts"
        )
        session = rescue_request(user=client_user, service=world, area=area())
        step(session)
        search = Assignment.objects.get(session=session, role="search")
        person = offset(SEA, 60, 60)
        report(
            session, search.vehicle, "person_detected", lat=person[0], lon=person[1], confidence=0.8
        )
        step(session)  # the team's server is down: the notice waits
        hook = Notice.objects.get(channel="webhook")
        assert hook.sent_at is None and hook.attempts == 1 and "503" in hook.last_error
        _Hook.status = 200
        missions_tick()
        notifications_send(session.pk)
        hook.refresh_from_db()
        assert hook.sent_at is not None
        keys = {key for key, _ in _Hook.seen}
        assert len(keys) == 1 and len(_Hook.seen) == 2  # one retry, same key
        body = _Hook.seen[-1][1]
        assert body["lat"] == pytest.approx(person[0]) and body["event"] == "person_in_water"
        assert len(mail.outbox) == 1
    finally:
        server.shutdown()


def test_a_notice_being_sent_by_another_worker_is_not_sent_again(world, client_user):
    session = rescue_request(user=client_user, service=world, area=area())
    step(session)
    search = Assignment.objects.get(session=session, role="search")
    person = offset(SEA, 60, 60)
    # Another worker holds the e-mail (it is sending it right now).
    report(session, search.vehicle, "person_detected", lat=person[0], lon=person[1])
    with time_machine.travel(timezone.now()):
        m = mission(session)
        m.session = session
        notices_create(m)
    Notice.objects.filter(channel="email").update(
        claimed_until=timezone.now() + timedelta(seconds=30), attempts=1
    )
    notifications_send(session.pk)
    step(session)
    assert len(mail.outbox) == 0
    email = Notice.objects.get(channel="email")
    assert email.sent_at is None and email.attempts == 1
    # That worker died mid-send: once its claim lapses the notice goes out, once.
    with time_machine.travel(timezone.now() + timedelta(seconds=31)):
        notifications_send(session.pk)
        notifications_send(session.pk)
    assert len(mail.outbox) == 1
    email.refresh_from_db()
    assert email.sent_at is not None and email.attempts == 2


def test_a_rescue_requested_through_the_api_runs_its_workflow(world, client_user) -> None:
    """The API starts a rescue exactly as the portal's map does: a mission over the
    area, whose workflow reserves and tasks the search drone; nothing is stranded."""
    from django.test import Client

    from accounts.tokens import token_issue

    token = token_issue(user=client_user, name="tests")
    body = {"service": "rescue-at-sea", "params": {"area": area(), "altitude_m": 40}}
    response = Client().post(
        "/api/v1/sessions",
        json.dumps(body),
        content_type="application/json",
        HTTP_AUTHORIZATION=f"Bearer {token}",
    )
    assert response.status_code == 201, response.content
    assert response.json()["task"] is None
    session = Session.objects.get(pk=response.json()["session"]["id"])
    assert mission(session).altitude_m == 40
    assert step(session) == Mission.State.SEARCHING
    assert session.events.filter(kind="task_deployed").exists()

    # Without an area there is nothing to search: refused, nothing recorded.
    bad = Client().post(
        "/api/v1/sessions",
        json.dumps({"service": "rescue-at-sea"}),
        content_type="application/json",
        HTTP_AUTHORIZATION=f"Bearer {token}",
    )
    assert bad.status_code == 400 and bad.json()["error"]["field"] == "params.area"
    assert Session.objects.count() == 1


def test_the_page_says_what_is_happening_and_how_long_it_will_take(world, client_user) -> None:
    # Not "0 of 12 waypoints" for minutes: on the way to the area, with the distance and
    # the time; then searching with the pattern left; then the life jacket on its way.
    from agents.geo import distance_m

    session = rescue_request(user=client_user, service=world, area=area())
    step(session)
    m = mission(session)
    search = Assignment.objects.get(session=session, role="search").vehicle
    phase = mission_json(m)["phase"]
    assert phase["label"] == "on the way to the search area"
    assert search.lat is not None and search.lon is not None
    first = distance_m((search.lat, search.lon), tuple(m.path[0]))
    assert phase["detail"] == f"{first:,.0f} m to the first of {len(m.path)} waypoints"
    speed = min(search.attributes["max_speed_mps"], m.speed_mps)
    assert phase["eta_s"] == pytest.approx(phase["remaining_m"] / speed, abs=1)
    assert phase["remaining_m"] > first  # the whole pattern after it

    # Over the third waypoint: what is left is the rest of the pattern.
    Mission.objects.filter(pk=m.pk).update(progress=2)
    Vehicle.objects.filter(pk=search.pk).update(lat=m.path[2][0], lon=m.path[2][1])
    m = mission(session)
    phase = mission_json(m)["phase"]
    assert phase["label"] == "searching"
    assert phase["detail"] == f"waypoint 3 of {len(m.path)} reached"
    left = sum(
        distance_m(tuple(m.path[i]), tuple(m.path[i + 1])) for i in range(2, len(m.path) - 1)
    )
    assert phase["remaining_m"] == pytest.approx(left, abs=1)

    # Waiting is not a countdown.
    Mission.objects.filter(pk=m.pk).update(state=Mission.State.WAITING_DELIVERY)
    phase = mission_json(mission(session))["phase"]
    assert phase["eta_s"] is None and "waiting" in phase["label"]
