"""Parcel delivery, from the request to the drop-off: validation, the carrier chosen,
the workflow step by step, a carrier lost with the parcel on board, cancelling, the
recipient's notices and tracking page.

Agents are stood in for by their reports, published as the uplink does.
"""

from __future__ import annotations

import json
from datetime import timedelta
from typing import Any

import pytest
from django.core import mail
from django.test import Client
from django.urls import reverse
from django.utils import timezone

from agents.geo import distance_m, offset
from agents.missions.spec import MissionSpec
from agents.protocol import parse_message
from fleet.models import Vehicle
from fleet.vehicle_events import vehicle_events
from kinds.parcel_delivery.missions import vehicle_mission
from kinds.parcel_delivery.models import Delivery
from kinds.parcel_delivery.presentation import delivery_json
from kinds.parcel_delivery.workflow import delivery_advance
from services.kinds import Request, RequestError
from services.models import Assignment, Service, Session
from services.sessions.ending import session_end
from services.sessions.matching import AssignmentError
from services.sessions.notices import notices_send
from services.sessions.request import service_request
from tests import factories as f

pytestmark = pytest.mark.django_db

#: On land: near the campus station (south-west of it: north-east is a pond), and 600 m
#: north-east of it.
LAND_A = offset(f.HOME, -100, -100)
LAND_B = offset(f.HOME, 500, 400)
#: At sea, west of the beach: a boat may take a parcel between these.
SEA_A = (40.6440, -8.7600)
SEA_B = (40.6500, -8.7700)


def wire(spec: MissionSpec | None) -> dict[str, Any]:
    """The mission as it travels in the signed task (the JSON the agent decodes)."""
    assert spec is not None
    return spec.to_payload()


@pytest.fixture
def world() -> dict[str, Any]:
    campus = f.station(name="Campus")
    beach = f.station(name="Beach", lat_lon=f.COAST, environments=["land", "sea", "air"])
    drone = f.vehicle(
        station=campus,
        vtype=f.vehicle_type("aerial", "mavlink"),
        name="drone-1",
        max_payload_kg=2.0,
        features=["payload_release"],
    )
    boat = f.vehicle(
        station=beach,
        vtype=f.vehicle_type("aquatic", "mavlink"),
        name="boat-1",
        max_payload_kg=20.0,
        max_range_m=20000,
        endurance_min=120,
        max_speed_mps=4,
        max_altitude_m=0.1,
        environments=["sea"],
        features=["payload_release"],
        cameras=["rgb"],
    )
    service = f.service(
        "parcels",
        kind="parcel_delivery",
        failsafe_action="return_to_home",
        roles=[
            {
                "name": "carrier",
                "kinds": ["aerial", "aquatic"],
                "features": ["payload_release"],
                "selection": "fastest",
                "required": False,
            }
        ],
    )
    return {"drone": drone, "boat": boat, "service": service, "user": f.user(username="sam")}


def params(a: tuple[float, float], b: tuple[float, float], **extra: Any) -> dict[str, Any]:
    return {
        "pickup": {"lat": a[0], "lon": a[1]},
        "dropoff": {"lat": b[0], "lon": b[1]},
        "weight_kg": 1.0,
        "recipient": {"name": "Rita", "email": "rita@example.org"},
        **extra,
    }


def request(world: dict[str, Any], p: dict[str, Any]) -> Session:
    return service_request(
        user=world["user"], service=world["service"], request=Request(params=p)
    ).session


def step(session: Session) -> str | None:
    """One step, then the notices it owed, as a worker runs both."""
    state = delivery_advance(session.pk)
    notices_send(session.pk)
    return state


def say(vehicle: Vehicle, session: Session, msg: dict[str, Any]) -> None:
    message = parse_message(
        json.dumps({"session_id": str(session.pk), **msg}), channel="uplink_to_platform"
    )
    vehicle_events().agent_message(vehicle_id=str(vehicle.pk), message=message)


def report(vehicle: Vehicle, session: Session, name: str, **data: Any) -> None:
    say(vehicle, session, {"type": "event", "event": name, "data": data})


def delivery(session: Session) -> Delivery:
    return Delivery.objects.get(pk=session.pk)


def carrier(session: Session) -> Assignment:
    return Assignment.objects.select_related("vehicle").get(
        session=session, role="carrier", active=True
    )


# --- requests -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"pickup": None}, "params.pickup"),
        ({"dropoff": {"lat": 95, "lon": 0}}, "params.dropoff.lat"),
        ({"dropoff": {"lat": LAND_A[0], "lon": LAND_A[1]}}, "params.dropoff"),
        ({"weight_kg": 0}, "params.weight_kg"),
        ({"weight_kg": 26}, "params.weight_kg"),
        ({"weight_kg": True}, "params.weight_kg"),
        ({"recipient": {"email": "not an address"}}, "params.recipient.email"),
        ({"recipient": {"webhook": "ftp://x"}}, "params.recipient.webhook"),
        ({"recipient": {"phone": "1"}}, "params.recipient.phone"),
        ({"colour": "red"}, "params.colour"),
    ],
)
def test_a_request_it_cannot_take_is_refused_naming_the_field(world, change, field) -> None:
    p = {**params(LAND_A, LAND_B), **change}
    if change.get("pickup", ...) is None:
        del p["pickup"]
    with pytest.raises(RequestError) as refused:
        request(world, p)
    assert refused.value.field == field
    assert not Session.objects.exists()


def test_a_request_through_the_api_is_the_same_request(world) -> None:
    from accounts.tokens import token_issue

    token = token_issue(user=world["user"], name="tests")
    body = {"service": "parcels", "params": params(LAND_A, LAND_B)}
    answer = Client().post(
        "/api/v1/sessions",
        json.dumps(body),
        content_type="application/json",
        HTTP_AUTHORIZATION=f"Bearer {token}",
    )
    assert answer.status_code == 201, answer.content
    assert Delivery.objects.get(pk=answer.json()["session"]["id"]).weight_kg == 1.0
    bad = Client().post(
        "/api/v1/sessions",
        json.dumps({"service": "parcels", "params": params(LAND_A, LAND_B, weight_kg=99)}),
        content_type="application/json",
        HTTP_AUTHORIZATION=f"Bearer {token}",
    )
    assert bad.status_code == 400 and bad.json()["error"]["field"] == "params.weight_kg"


# --- the carrier --------------------------------------------------------------------------


def test_over_land_a_drone_carries_it_even_when_a_boat_is_nearer(world) -> None:
    Vehicle.objects.filter(pk=world["boat"].pk).update(lat=LAND_A[0], lon=LAND_A[1])
    session = request(world, params(LAND_A, LAND_B))
    assert not delivery(session).over_water
    assert step(session) == Delivery.State.TO_PICKUP
    assert carrier(session).vehicle.name == "drone-1"


def test_between_two_points_at_sea_the_boat_may_carry_it(world) -> None:
    Vehicle.objects.filter(pk=world["drone"].pk).update(status=Vehicle.Status.OFFLINE)
    session = request(world, params(SEA_A, SEA_B))
    assert delivery(session).over_water
    assert step(session) == Delivery.State.TO_PICKUP
    assert carrier(session).vehicle.name == "boat-1"


def test_a_parcel_too_heavy_for_any_drone_is_refused_at_once_saying_what_would_work(
    world,
) -> None:
    with pytest.raises(RequestError) as refused:
        request(world, params(LAND_A, LAND_B, weight_kg=5))
    assert refused.value.field == "params.weight_kg"
    assert str(refused.value) == (
        "no vehicle carries 5 kg by air: the heaviest parcel is 2 kg (drone-1); boat-1 "
        "carries up to 20 kg between two points on the water"
    )
    assert not Session.objects.exists()


def test_a_parcel_whose_drone_is_busy_waits_and_says_so(world) -> None:
    Vehicle.objects.filter(pk=world["drone"].pk).update(status=Vehicle.Status.IN_SERVICE)
    session = request(world, params(LAND_A, LAND_B))
    assert step(session) == Delivery.State.WAITING_CARRIER
    assert delivery(session).status_text == (
        "waiting for a vehicle: drone-1 is busy with another session: this request is next in line"
    )


# --- the workflow --------------------------------------------------------------------------


def test_from_pickup_to_drop_off_with_the_recipient_told(world) -> None:
    session = request(world, params(LAND_A, LAND_B))
    assert step(session) == Delivery.State.TO_PICKUP
    drone = carrier(session)
    doc = wire(vehicle_mission(assignment=drone))
    assert doc["kind"] == "parcel"
    assert doc["pickup"] == list(LAND_A) and doc["dropoff"] == list(LAND_B)
    say(drone.vehicle, session, {"type": "task_accepted"})
    assert Session.objects.get(pk=session.pk).state == Session.State.ACTIVE

    report(drone.vehicle, session, "parcel_loaded", mission=doc["id"])
    assert step(session) == Delivery.State.TO_DROPOFF
    (dispatched,) = mail.outbox
    assert dispatched.to == ["rita@example.org"]
    assert reverse("parcel_track", args=[delivery(session).tracking_token]) in dispatched.body

    report(drone.vehicle, session, "payload_released", mission=doc["id"])
    assert step(session) == Delivery.State.DELIVERED
    session.refresh_from_db()
    assert session.state == Session.State.ENDED
    assert len(mail.outbox) == 2 and "delivered" in mail.outbox[1].subject
    # A repeated report or step changes nothing and tells nobody twice.
    report(drone.vehicle, session, "payload_released", mission=doc["id"])
    step(session)
    assert len(mail.outbox) == 2


def test_a_mission_the_autopilot_refused_is_logged_and_shown_as_flown_step_by_step(
    world,
) -> None:
    """The carrier's autopilot refused the plan (agents/missions/kit.py: fly_natively):
    the log and the user's timeline say so, nothing else changes."""
    session = request(world, params(LAND_A, LAND_B))
    step(session)
    drone = carrier(session)
    reason = "the autopilot refused the mission: MAV_MISSION_NO_SPACE (more items than it stores)"
    report(drone.vehicle, session, "native_mission_refused", mission="m", reason=reason)
    entry = session.events.get(kind="native_mission_refused").data
    assert entry["reason"] == reason and entry["vehicle"] == str(drone.vehicle_id)
    assert step(session) == Delivery.State.TO_PICKUP
    timeline = delivery_json(delivery(session))["timeline"]
    assert [e["data"]["reason"] for e in timeline if e["kind"] == "native_mission_refused"] == [
        reason
    ]


def spare_drone(world: dict[str, Any]) -> Vehicle:
    """A second payload drone at the station, 300 m south of home."""
    return f.vehicle(
        station=world["drone"].station,
        vtype=world["drone"].vehicle_type,
        name="drone-2",
        max_payload_kg=2.0,
        features=["payload_release"],
        at=offset(f.HOME, -300, 0),
    )


def test_a_carrier_lost_with_the_parcel_hands_it_over_where_it_is(world, settings) -> None:
    spare = spare_drone(world)
    session = request(world, params(LAND_A, LAND_B))
    step(session)
    first = carrier(session)
    report(first.vehicle, session, "parcel_loaded")
    step(session)
    # Mid-way, the drone drops off the network for longer than the grace.
    midway = offset(LAND_A, 200, 150)
    lost = timezone.now() - timedelta(seconds=settings.IOUV_MISSION_OFFLINE_GRACE_S + 1)
    Vehicle.objects.filter(pk=first.vehicle_id).update(
        status=Vehicle.Status.OFFLINE, lat=midway[0], lon=midway[1], last_seen=lost
    )
    assert step(session) == Delivery.State.TO_PICKUP
    second = carrier(session)
    assert second.vehicle_id == spare.pk
    d = delivery(session)
    assert distance_m(d.pickup, midway) < 1 and d.loaded_at is None
    assert wire(vehicle_mission(assignment=second))["pickup"] == list(d.pickup)
    released = session.events.get(kind="vehicle_released").data
    assert released["cause"] == "offline" and released["vehicle_name"] == "drone-1"


def test_a_carrier_whose_autopilot_flies_on_alone_is_waited_for_then_replaced(
    world, settings
) -> None:
    """The carrier's autopilot flies the delivery itself (native_mission_started, at most
    300 s) and its agent goes silent: the autopilot delivers without it, so nobody else
    is sent to collect the parcel until those 300 s are past."""
    spare = spare_drone(world)
    session = request(world, params(LAND_A, LAND_B))
    step(session)
    first = carrier(session)
    report(first.vehicle, session, "native_mission_started", mission="m", within_s=300)
    report(first.vehicle, session, "parcel_loaded")
    step(session)
    lost = timezone.now() - timedelta(seconds=settings.IOUV_MISSION_OFFLINE_GRACE_S + 1)
    Vehicle.objects.filter(pk=first.vehicle_id).update(
        status=Vehicle.Status.OFFLINE, last_seen=lost
    )
    assert step(session) == Delivery.State.TO_DROPOFF
    assert carrier(session).pk == first.pk
    assert not session.events.filter(kind="vehicle_released").exists()
    timeline = delivery_json(delivery(session))["timeline"]
    assert [e["data"]["within_s"] for e in timeline if e["kind"] == "native_mission_started"] == [
        300
    ]
    # Past the time the autopilot may take: the parcel is looked for where it was.
    session.events.filter(kind="native_mission_started").update(
        created_at=timezone.now() - timedelta(seconds=301)
    )
    assert step(session) == Delivery.State.TO_PICKUP
    assert carrier(session).vehicle_id == spare.pk
    assert session.events.get(kind="vehicle_released").data["cause"] == "offline"


@pytest.mark.parametrize(
    ("within_s", "failed"), [(300, True), ("300", False), (True, False), (-5, False)]
)
def test_a_mission_the_carrier_gave_up_or_a_word_without_a_time_is_not_waited_for(
    world, settings, within_s, failed
) -> None:
    session = request(world, params(LAND_A, LAND_B))
    step(session)
    first = carrier(session)
    report(first.vehicle, session, "native_mission_started", mission="m", within_s=within_s)
    if failed:
        report(first.vehicle, session, "mission_failed", mission="m", reason="fence breached")
    lost = timezone.now() - timedelta(seconds=settings.IOUV_MISSION_OFFLINE_GRACE_S + 1)
    Vehicle.objects.filter(pk=first.vehicle_id).update(
        status=Vehicle.Status.OFFLINE, last_seen=lost
    )
    step(session)
    assert not Assignment.objects.get(pk=first.pk).active


def test_the_user_cancels_and_the_carrier_is_called_back(world) -> None:
    session = request(world, params(LAND_A, LAND_B))
    step(session)
    session_end(session=session, reason="cancelled by the user", by_user=True)
    assert step(session) == Delivery.State.CANCELLED
    assert "cancelled" in delivery(session).status_text


# --- the recipient's page ----------------------------------------------------------------


def test_the_recipient_follows_it_without_an_account(world) -> None:
    session = request(world, params(LAND_A, LAND_B))
    step(session)
    token = delivery(session).tracking_token
    page = Client().get(reverse("parcel_track", args=[token]))
    assert page.status_code == 200 and "no-store" in page["Cache-Control"]
    state = Client().get(reverse("parcel_track_state", args=[token])).json()
    assert state["state"] == "to_pickup" and state["eta_s"] > 0
    assert "timeline" not in state  # the session's log is its user's
    assert Client().get(reverse("parcel_track", args=["not-a-token"])).status_code == 404


def test_the_delivery_state_is_its_users_and_the_monitors(world) -> None:
    session = request(world, params(LAND_A, LAND_B))
    url = reverse("parcel_state", args=[session.pk])
    stranger = Client()
    stranger.force_login(f.user(username="eve"))
    assert stranger.get(url).status_code == 404
    owner = Client()
    owner.force_login(world["user"])
    assert owner.get(url).json()["state"] == "waiting_carrier"


def test_a_request_without_a_grant_is_refused(world) -> None:
    Service.objects.filter(pk=world["service"].pk).update(is_active=False)
    with pytest.raises(AssignmentError):
        request(world, params(LAND_A, LAND_B))
