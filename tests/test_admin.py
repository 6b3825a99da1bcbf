"""The Django admin over the seeded demo world, driven through the test client."""

from __future__ import annotations

import json
from typing import Any

import pytest
from django.contrib.admin.models import LogEntry
from django.contrib.auth import get_user_model
from django.contrib.sessions.models import Session as WebSession
from django.test import Client
from django.urls import reverse

from fleet.credentials import vehicle_authenticate
from fleet.models import Station, Vehicle, VehicleType
from services.demo import demo_seed
from services.models import Service, Session, SessionEvent
from services.sessions.log import event_append

pytestmark = pytest.mark.django_db

PASSWORD = "admin-test-password"
CHANGELIST = "admin:fleet_vehicle_changelist"


@pytest.fixture(autouse=True)
def _fast_hasher(settings: Any) -> None:
    settings.PASSWORD_HASHERS = ["django.contrib.auth.hashers.MD5PasswordHasher"]


@pytest.fixture
def seeded() -> None:
    demo_seed(password=PASSWORD)


def _login(username: str) -> Client:
    client = Client()
    assert client.login(username=username, password=PASSWORD)
    return client


@pytest.fixture
def as_admin(seeded: None) -> Client:
    return _login("admin")


@pytest.fixture
def as_operator(seeded: None) -> Client:
    return _login("operator")


def _names(response: Any) -> set[str]:
    return {v.name for v in response.context["cl"].result_list}


def _action(client: Client, action: str, *vehicles: Vehicle, follow: bool = False) -> Any:
    return client.post(
        reverse(CHANGELIST),
        {"action": action, "_selected_action": [str(v.pk) for v in vehicles]},
        follow=follow,
    )


def _action_names(client: Client, changelist: str = CHANGELIST) -> set[str]:
    response = client.get(reverse(changelist))
    assert response.status_code == 200
    form = response.context["action_form"]  # None when no action is allowed
    return {name for name, _ in form.fields["action"].choices if name} if form else set()


# --- vehicles: list, filters, search ---------------------------------------------------


def test_vehicle_changelist_lists_the_fleet(as_admin: Client) -> None:
    response = as_admin.get(reverse(CHANGELIST))
    assert response.status_code == 200
    names = {
        *("car-1", "car-2", "car-3", "car-4", "quad-1", "vtol-1"),
        *("search-1", "lifeguard-1", "boat-1"),
    }
    assert _names(response) == names
    for name in names:
        assert name in response.content.decode()


def test_the_battery_reads_in_whole_percents(as_admin: Client) -> None:
    Vehicle.objects.filter(name="quad-1").update(battery=99.59783016905)
    page = as_admin.get(reverse(CHANGELIST)).content.decode()
    assert "100 %" in page and "99.597" not in page
    quad = Vehicle.objects.get(name="quad-1")
    detail = as_admin.get(reverse("admin:fleet_vehicle_change", args=[quad.pk])).content.decode()
    assert "100 %" in detail and "99.597" not in detail


def test_vehicle_filters_by_station_and_status(as_admin: Client) -> None:
    coast = Station.objects.get(name="Costa Nova station")
    response = as_admin.get(reverse(CHANGELIST), {"station__id__exact": coast.pk})
    assert response.status_code == 200
    assert _names(response) == {"search-1", "lifeguard-1", "boat-1"}

    Vehicle.objects.filter(name="quad-1").update(status=Vehicle.Status.IDLE)
    response = as_admin.get(reverse(CHANGELIST), {"status__exact": "idle"})
    assert response.status_code == 200
    assert _names(response) == {"quad-1"}


def test_vehicle_search_by_name_station_and_id(as_admin: Client) -> None:
    quad = Vehicle.objects.get(name="quad-1")
    assert _names(as_admin.get(reverse(CHANGELIST), {"q": "vtol"})) == {"vtol-1"}
    assert _names(as_admin.get(reverse(CHANGELIST), {"q": "Costa"})) == {
        "search-1",
        "lifeguard-1",
        "boat-1",
    }
    assert _names(as_admin.get(reverse(CHANGELIST), {"q": str(quad.pk)})) == {"quad-1"}


def test_other_changelists_render(as_admin: Client) -> None:
    for name in (
        "admin:fleet_station_changelist",
        "admin:fleet_vehicletype_changelist",
        "admin:services_service_changelist",
        "admin:services_session_changelist",
        "admin:services_sessionevent_changelist",
        "admin:services_assignment_changelist",
        "admin:fleet_vehicle_add",
    ):
        assert as_admin.get(reverse(name)).status_code == 200, name
    services = as_admin.get(reverse("admin:services_service_changelist")).content.decode()
    for slug in ("drive-car", "fly-drone", "fly-vtol", "spectate", "rescue-at-sea"):
        assert slug in services
    rescue = Service.objects.get(slug="rescue-at-sea")
    page = as_admin.get(reverse("admin:services_service_change", args=[rescue.pk]))
    assert page.status_code == 200
    assert "delivery" in page.content.decode()


# --- credentials -------------------------------------------------------------------------


def test_issue_credential_is_shown_once_and_authenticates(as_admin: Client) -> None:
    car = Vehicle.objects.get(name="car-2")
    response = _action(as_admin, "issue_credential", car)
    assert response.status_code == 200
    assert "no-store" in response["Cache-Control"]
    (row,) = response.context["issued"]
    credential = row.credential
    assert credential in response.content.decode()

    car.refresh_from_db()
    assert car.credential_hash and car.credential_hash != credential
    assert car.credential_issued_at is not None
    assert vehicle_authenticate(vehicle_id=str(car.pk), credential=credential) == car

    # Never again: not on the next page, not in the admin log, not in the web session.
    assert credential not in as_admin.get(reverse(CHANGELIST)).content.decode()
    change = as_admin.get(reverse("admin:fleet_vehicle_change", args=[car.pk]))
    assert credential not in change.content.decode()
    assert LogEntry.objects.filter(object_id=str(car.pk)).exists()
    for entry in LogEntry.objects.all():
        assert credential not in entry.change_message
    for stored in WebSession.objects.all():
        assert credential not in json.dumps(stored.get_decoded())


def test_issue_credential_for_several_vehicles(as_admin: Client) -> None:
    cars = list(Vehicle.objects.filter(name__in=["car-3", "car-4"]))
    response = _action(as_admin, "issue_credential", *cars)
    issued = {row.vehicle.name: row.credential for row in response.context["issued"]}
    assert set(issued) == {"car-3", "car-4"}
    assert issued["car-3"] != issued["car-4"]
    for car in cars:
        assert vehicle_authenticate(vehicle_id=str(car.pk), credential=issued[car.name])


# --- attributes validation -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("change", "field", "detail"),
    [
        ({"max_range_m": -5}, "max_range_m", "zero or more"),
        ({"cameras": ["rgb", "xray"]}, "cameras", "xray"),
        ({"max_payload_kg": "heavy"}, "max_payload_kg", "number"),
    ],
)
def test_bad_attributes_are_refused_naming_the_field(
    as_admin: Client, change: dict[str, Any], field: str, detail: str
) -> None:
    car = Vehicle.objects.get(name="car-1")
    before = dict(car.attributes)
    response = as_admin.post(
        reverse("admin:fleet_vehicle_change", args=[car.pk]),
        {
            "name": car.name,
            "vehicle_type": car.vehicle_type_id,
            "station": car.station_id,
            "attributes": json.dumps({**before, **change}),
        },
    )
    assert response.status_code == 200  # the form again, not a redirect
    errors = response.context["adminform"].form.errors["attributes"]
    assert any(field in e and detail in e for e in errors), errors
    assert field in response.content.decode()
    car.refresh_from_db()
    assert car.attributes == before


def test_good_attributes_are_saved_normalised(as_admin: Client) -> None:
    car = Vehicle.objects.get(name="car-2")
    attributes = {**car.attributes, "max_range_m": 2500, "cameras": ["thermal", "rgb"]}
    response = as_admin.post(
        reverse("admin:fleet_vehicle_change", args=[car.pk]),
        {
            "name": car.name,
            "vehicle_type": car.vehicle_type_id,
            "station": car.station_id,
            "attributes": json.dumps(attributes),
            # A live field in the POST is ignored: the form does not have it.
            "status": "idle",
        },
    )
    assert response.status_code == 302
    car.refresh_from_db()
    assert car.attributes["max_range_m"] == 2500.0
    assert car.attributes["cameras"] == ["rgb", "thermal"]
    assert car.status == Vehicle.Status.OFFLINE


def test_bad_command_vocabulary_is_refused(as_admin: Client) -> None:
    car_type = VehicleType.objects.get(name="Raspberry Pi car")
    commands = [{"name": "forward", "args": {"speed": {"type": "number", "min": 2, "max": 1}}}]
    response = as_admin.post(
        reverse("admin:fleet_vehicletype_change", args=[car_type.pk]),
        {
            "name": car_type.name,
            "kind": car_type.kind,
            "adapter": car_type.adapter,
            "description": "",
            "commands": json.dumps(commands),
        },
    )
    assert response.status_code == 200
    assert "commands[0].args.speed.min" in response.content.decode()


# --- maintenance ---------------------------------------------------------------------------


def test_maintenance_actions_move_a_vehicle_out_and_back(as_admin: Client) -> None:
    quad = Vehicle.objects.get(name="quad-1")
    response = _action(as_admin, "put_in_maintenance", quad)
    assert response.status_code == 302
    quad.refresh_from_db()
    assert quad.maintenance and quad.status == Vehicle.Status.MAINTENANCE

    _action(as_admin, "return_to_service", quad)
    quad.refresh_from_db()
    assert not quad.maintenance and quad.status == Vehicle.Status.OFFLINE


def test_maintenance_refused_for_a_busy_vehicle_is_reported(as_admin: Client) -> None:
    Vehicle.objects.filter(name="car-1").update(status=Vehicle.Status.IN_SERVICE)
    busy, free = Vehicle.objects.get(name="car-1"), Vehicle.objects.get(name="car-2")
    response = _action(as_admin, "put_in_maintenance", busy, free, follow=True)
    texts = [(m.level_tag, str(m)) for m in response.context["messages"]]
    assert any(tag == "error" and "car-1" in text for tag, text in texts), texts
    assert any(tag == "success" and "car-2" in text for tag, text in texts), texts
    busy.refresh_from_db()
    free.refresh_from_db()
    assert not busy.maintenance and busy.status == Vehicle.Status.IN_SERVICE
    assert free.maintenance


def test_operator_runs_maintenance_but_cannot_issue_credentials(as_operator: Client) -> None:
    actions = _action_names(as_operator)
    assert {"put_in_maintenance", "return_to_service"} <= actions
    assert "issue_credential" not in actions

    car = Vehicle.objects.get(name="car-3")
    _action(as_operator, "put_in_maintenance", car)
    car.refresh_from_db()
    assert car.maintenance

    response = _action(as_operator, "issue_credential", car)
    assert response.status_code == 302  # refused as "no action selected"
    car.refresh_from_db()
    assert car.credential_hash == ""


def test_monitor_sees_the_fleet_without_actions(seeded: None) -> None:
    monitor = _login("monitor")
    actions = _action_names(monitor)
    assert not actions & {"put_in_maintenance", "return_to_service", "issue_credential"}


# --- sessions and their log ------------------------------------------------------------------


@pytest.fixture
def session_with_log(seeded: None) -> Session:
    session = Session.objects.create(
        service=Service.objects.get(slug="drive-car"),
        user=get_user_model().objects.get(username="client"),
    )
    for kind in ("requested", "assigned", "command"):
        event_append(session=session, kind=kind, data={"note": kind})
    return session


def test_session_admin_shows_the_log_chain(as_admin: Client, session_with_log: Session) -> None:
    url = reverse("admin:services_session_change", args=[session_with_log.pk])
    page = as_admin.get(url)
    assert page.status_code == 200
    assert "OK with 3 events" in page.content.decode()

    # Tamper with the stored row behind the ORM's back (QuerySet.update skips save()).
    SessionEvent.objects.filter(session=session_with_log, seq=2).update(data={"note": "x"})
    page = as_admin.get(url)
    assert "broken at #2" in page.content.decode()


def test_session_admin_is_read_only(as_admin: Client, session_with_log: Session) -> None:
    url = reverse("admin:services_session_change", args=[session_with_log.pk])
    assert as_admin.post(url, {"state": "ended", "reason": "x"}).status_code == 403
    assert as_admin.get(reverse("admin:services_session_add")).status_code == 403
    session_with_log.refresh_from_db()
    assert session_with_log.state == Session.State.REQUESTED
    listed = as_admin.get(reverse("admin:services_session_changelist"))
    assert str(session_with_log.pk) in listed.content.decode()


def test_session_event_admin_refuses_change_and_delete(
    as_admin: Client, session_with_log: Session
) -> None:
    event = SessionEvent.objects.get(session=session_with_log, seq=1)
    change = reverse("admin:services_sessionevent_change", args=[event.pk])
    assert as_admin.get(change).status_code == 200  # view only
    assert as_admin.post(change, {"kind": "forged", "seq": 1}).status_code == 403
    delete = reverse("admin:services_sessionevent_delete", args=[event.pk])
    assert as_admin.get(delete).status_code == 403
    assert as_admin.post(delete, {"post": "yes"}).status_code == 403
    assert as_admin.get(reverse("admin:services_sessionevent_add")).status_code == 403
    assert "delete_selected" not in _action_names(
        as_admin, "admin:services_sessionevent_changelist"
    )
    event.refresh_from_db()
    assert event.kind == "requested"
    assert SessionEvent.objects.filter(session=session_with_log).count() == 3
