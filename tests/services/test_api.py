"""The JSON API, driven over HTTP through the test client and fuzzed against its own
(generated) OpenAPI document with schemathesis: operation by operation, and in
sequences that follow the document's links from a created session to the operations
on it."""

from __future__ import annotations

import asyncio
import json
import re
import uuid
from typing import Any

import pytest
import schemathesis
from django.contrib.staticfiles import finders
from django.core.handlers.wsgi import WSGIHandler
from django.core.signals import request_finished, request_started
from django.db import close_old_connections
from django.test import Client
from django.urls import URLPattern, URLResolver, get_resolver
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from openapi_spec_validator import validate as openapi_validate
from schemathesis.checks import not_a_server_error
from schemathesis.core.parameters import ParameterLocation
from schemathesis.generation import GenerationMode
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    negative_data_rejection,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from accounts.roles import CLIENT, MONITOR
from accounts.tokens import token_for_raw, token_issue, token_revoke
from agents.protocol import UserGrant
from fleet.models import Vehicle
from services.models import Service, Session
from services.sessions.signing import platform_public_key
from services.web import api
from tests import factories as f

pytestmark = pytest.mark.django_db

COMMANDS = [
    {"name": "up", "args": {}},
    {"name": "down", "args": {}},
    {"name": "stop", "args": {}},
]
TARGET = {"lat": 40.6310, "lon": -8.6590}


# --- rows and a client ---------------------------------------------------------------------


@pytest.fixture
def drone() -> Vehicle:
    """An online idle drone at a station, with the profile its agent would report."""
    vehicle = f.vehicle(station=f.station(name="Campus"), vtype=f.vehicle_type(), name="drone-1")
    Vehicle.objects.filter(pk=vehicle.pk).update(
        control_url="ws://10.0.0.7:8765/control",
        profile={"commands": COMMANDS, "telemetry": ["position", "battery"], "video": True},
    )
    vehicle.refresh_from_db()
    return vehicle


@pytest.fixture
def fly() -> Service:
    return f.service(
        "fly",
        allowed_commands=["up", "stop"],
        description="Fly a drone.",
        failsafe_action=Service.Failsafe.LAND,
        max_altitude_m=30,
        geofence_radius_m=200,
    )


def _token(username: str, *roles: str) -> str:
    return token_issue(user=f.user(username=username, roles=roles), name="tests")


@pytest.fixture
def alice() -> str:
    return _token("alice", CLIENT)


@pytest.fixture
def bob() -> str:
    return _token("bob", CLIENT)


@pytest.fixture
def monitor() -> str:
    return _token("mona", MONITOR)


def call(
    method: str,
    path: str,
    *,
    token: str | None = None,
    body: Any = None,
    raw: str | bytes | None = None,
    client: Client | None = None,
    **headers: str,
) -> Any:
    """``method`` on /api/v1``path``; ``body`` is sent as JSON, ``raw`` as is."""
    if token is not None:
        headers["HTTP_AUTHORIZATION"] = f"Bearer {token}"
    data = raw if raw is not None else ("" if body is None else json.dumps(body))
    return (client or Client()).generic(
        method, f"/api/v1{path}", data, content_type="application/json", **headers
    )


def _error(response: Any, status: int, code: str) -> dict[str, Any]:
    assert response.status_code == status, response.content
    assert response["Content-Type"] == "application/json"
    error = response.json()["error"]
    assert error["code"] == code and error["message"]
    return error


@pytest.fixture
def requested(drone: Vehicle, fly: Service, alice: str) -> dict[str, Any]:
    """The 201 body of alice's request for the drone."""
    response = call("POST", "/sessions", token=alice, body={"service": "fly", "target": TARGET})
    assert response.status_code == 201, response.content
    return response.json()


# --- services ------------------------------------------------------------------------------


def test_services_lists_what_the_user_may_request(fly: Service, alice: str):
    f.service("hidden", grant_clients=False)
    f.service("off", is_active=False)
    response = call("GET", "/services", token=alice)
    assert response.status_code == 200
    assert "no-store" in response["Cache-Control"]
    (service,) = response.json()["services"]
    assert service["slug"] == "fly" and service["name"] == "fly"
    assert service["description"] == "Fly a drone." and service["mode"] == "sync"
    assert service["commands"] == ["up", "stop"]
    assert service["roles"][0]["name"] == "vehicle" and service["roles"][0]["min_battery"] == 30
    assert service["limits"]["failsafe_action"] == "land"
    assert service["limits"]["max_altitude_m"] == 30
    assert service["limits"]["max_speed_mps"] is None


def test_services_is_empty_for_a_user_without_the_client_role(fly: Service, monitor: str):
    assert call("GET", "/services", token=monitor).json() == {"services": []}


# --- requesting a session ------------------------------------------------------------------


def test_request_reserves_the_vehicle_and_returns_the_user_task(requested, drone):
    session, task = requested["session"], requested["task"]
    assert session["state"] == "assigned" and session["user"] == "alice"
    assert session["service"] == {"slug": "fly", "name": "fly", "mode": "sync"}
    assert session["target"] == TARGET and session["relay"] is False
    assert session["assignments"][0]["vehicle"] == {"id": str(drone.pk), "name": "drone-1"}
    assert session["log"]["chain_ok"] is True
    assert [e["kind"] for e in session["log"]["events"]][:3] == ["requested", "assigned", "state"]

    assert task["control_url"] == "ws://10.0.0.7:8765/control" and task["relay"] is False
    assert task["vehicle_id"] == str(drone.pk) and task["vehicle_name"] == "drone-1"
    assert [c["name"] for c in task["commands"]] == ["up", "stop"]
    assert task["telemetry"] == ["position", "battery"]
    grant = UserGrant.verify(task["grant"], platform_public_key(), vehicle_id=str(drone.pk))
    assert (grant.session_id, grant.user, grant.role) == (session["id"], "alice", "controller")
    assert task["expires_at"] == grant.expires_at

    drone.refresh_from_db()
    assert drone.status == Vehicle.Status.RESERVED


def test_request_answers_201_with_the_location(drone, fly, alice):
    response = call("POST", "/sessions", token=alice, body={"service": "fly"})
    assert response.status_code == 201
    assert response["Location"] == f"/api/v1/sessions/{response.json()['session']['id']}"
    assert "no-store" in response["Cache-Control"]  # it carries a grant


def test_a_relayed_session_points_at_the_platform_relay(drone, fly, alice):
    body = {"service": "fly", "relay": True, "params": {"note": "ok"}}
    data = call("POST", "/sessions", token=alice, body=body).json()
    sid = data["session"]["id"]
    assert data["task"]["relay"] is True
    assert data["task"]["control_url"] == f"ws://testserver/ws/relay/{sid}/"
    assert data["session"]["params"] == {"note": "ok"}


def test_a_null_target_means_anywhere(drone, fly, alice):
    response = call("POST", "/sessions", token=alice, body={"service": "fly", "target": None})
    assert response.status_code == 201 and response.json()["session"]["target"] is None


def test_preferences_narrow_the_requirements(drone, fly, alice):
    body = {"service": "fly", "preferences": {"cameras": ["thermal"]}}
    error = _error(call("POST", "/sessions", token=alice, body=body), 422, "unmet_requirement")
    assert "thermal" in error["message"]


def test_a_service_whose_kind_is_not_installed_is_refused_and_holds_nothing(drone, alice):
    """Reserving its vehicles would strand them: nothing would ever run the session."""
    Service.objects.filter(pk=f.service("autonomous").pk).update(kind="not_installed")
    response = call("POST", "/sessions", token=alice, body={"service": "autonomous"})
    error = _error(response, 400, "invalid_field")
    assert error["field"] == "service" and "not installed" in error["message"]
    assert not Session.objects.exists()
    drone.refresh_from_db()
    assert drone.status == Vehicle.Status.IDLE


def test_an_unmeetable_request_is_422_with_the_reason(fly, alice):
    f.vehicle(station=f.station(), vtype=f.vehicle_type(), battery=10)
    response = call("POST", "/sessions", token=alice, body={"service": "fly"})
    error = _error(response, 422, "unmet_requirement")
    assert error["message"] == "vehicle: no idle vehicle has battery ≥ 30%"
    assert error["role"] == "vehicle"
    failed = Session.objects.get(pk=error["session_id"])
    assert failed.state == Session.State.FAILED and failed.reason == error["message"]


def test_no_vehicle_online_is_422(fly, alice):
    response = call("POST", "/sessions", token=alice, body={"service": "fly"})
    error = _error(response, 422, "unmet_requirement")
    assert "no vehicle is online and idle" in error["message"]


def test_a_service_whose_limits_cannot_be_signed_is_422_and_frees_the_vehicle(drone, alice):
    # Bypasses the model's validators, as a bad row in an old database would.
    f.service("broken", max_speed_mps=0)
    response = call("POST", "/sessions", token=alice, body={"service": "broken"})
    error = _error(response, 422, "invalid_task")
    assert Session.objects.get(pk=error["session_id"]).state == Session.State.FAILED
    drone.refresh_from_db()
    assert drone.status == Vehicle.Status.IDLE


def test_a_service_without_a_grant_is_403(drone, alice):
    f.service("private", grant_clients=False)
    response = call("POST", "/sessions", token=alice, body={"service": "private"})
    _error(response, 403, "permission_denied")
    assert not Session.objects.exists()


def test_a_user_without_the_client_role_cannot_request(drone, fly, monitor):
    response = call("POST", "/sessions", token=monitor, body={"service": "fly"})
    _error(response, 403, "permission_denied")


def test_spectating_is_not_requested_as_a_session(drone, alice):
    f.service("watch", kind="spectate")
    response = call("POST", "/sessions", token=alice, body={"service": "watch"})
    error = _error(response, 400, "invalid_field")
    assert error["field"] == "service"


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({}, "service"),
        ({"service": 5}, "service"),
        ({"service": ""}, "service"),
        ({"service": "nope"}, "service"),
        ({"service": "fly", "target": {"lat": 91, "lon": 0}}, "target.lat"),
        ({"service": "fly", "target": {"lat": 0, "lon": -180.5}}, "target.lon"),
        ({"service": "fly", "target": {"lat": "40", "lon": 0}}, "target.lat"),
        ({"service": "fly", "target": {"lat": True, "lon": 0}}, "target.lat"),
        ({"service": "fly", "target": {"lat": 40}}, "target.lon"),
        ({"service": "fly", "target": {"lat": 40, "lon": 0, "alt": 3}}, "target.alt"),
        ({"service": "fly", "target": [40, 0]}, "target"),
        ({"service": "fly", "relay": "yes"}, "relay"),
        ({"service": "fly", "params": []}, "params"),
        ({"service": "fly", "params": {"mission": {}}}, "params.mission"),
        ({"service": "fly", "params": {"a": "nul\x00"}}, "params.a"),
        ({"service": "fly", "params": {"a": "\ud800"}}, "params.a"),
        ({"service": "fly\x00"}, "service"),
        ({"service": "fly", "preferences": {"cameras": ["x-ray"]}}, "preferences.cameras"),
        ({"service": "fly", "preferences": {"min_battery": 101}}, "preferences.min_battery"),
        ({"service": "fly", "preferences": {"speed": 1}}, "preferences.speed"),
        ({"service": "fly", "preferences": None}, "preferences"),
        ({"service": "fly", "preferences": {"cameras": ["rgb", "rgb"]}}, "preferences.cameras"),
        ({"service": "fly", "params": {"\ud800": 1}}, "params"),
        ({"service": "fly", "serivce": "typo"}, "serivce"),
    ],
)
def test_invalid_fields_are_400_naming_the_field(drone, fly, alice, body, field):
    error = _error(call("POST", "/sessions", token=alice, body=body), 400, "invalid_field")
    assert error["field"] == field and field in error["message"]
    assert not Session.objects.exists()


def test_a_number_too_large_for_a_float_is_400(drone, fly, alice):
    raw = '{"service": "fly", "target": {"lat": 1e999, "lon": 0}}'  # parses as infinity
    error = _error(call("POST", "/sessions", token=alice, raw=raw), 400, "invalid_field")
    assert error["field"] == "target.lat"


def test_params_nested_too_deep_are_400(drone, fly, alice):
    deep: Any = 1
    for _ in range(api.PARAMS_MAX_DEPTH + 1):
        deep = [deep]
    body = {"service": "fly", "params": {"a": deep}}
    error = _error(call("POST", "/sessions", token=alice, body=body), 400, "invalid_field")
    assert error["field"].startswith("params.a[0]") and "deep" in error["message"]


@pytest.mark.parametrize(
    "raw",
    ["", "{", "[1]", '"fly"', "null", '{"service": NaN}', b"\xff\xfe{", "[" * 5000],
)
def test_bodies_that_are_not_a_json_object_are_400(fly, alice, raw):
    _error(call("POST", "/sessions", token=alice, raw=raw), 400, "invalid_json")


def test_a_body_over_64_kib_is_413(fly, alice):
    body = json.dumps({"service": "fly", "params": {"pad": "x" * 65_536}})
    _error(call("POST", "/sessions", token=alice, raw=body), 413, "payload_too_large")
    assert not Session.objects.exists()


# --- reading a session ---------------------------------------------------------------------


def test_the_owner_reads_the_session_and_its_log(requested, alice):
    sid = requested["session"]["id"]
    response = call("GET", f"/sessions/{sid}", token=alice)
    assert response.status_code == 200
    data = response.json()
    assert data["id"] == sid and data["state"] == "assigned"
    assert data["log"]["chain_ok"] is True and data["log"]["bad_seq"] is None
    kinds = [e["kind"] for e in data["log"]["events"]]
    assert kinds == ["requested", "assigned", "state", "task_deployed", "grant_issued"]
    assert [e["seq"] for e in data["log"]["events"]] == [1, 2, 3, 4, 5]
    assert all(e["created_at"] for e in data["log"]["events"])


def test_another_user_gets_404_for_a_session_not_theirs(requested, bob):
    sid = requested["session"]["id"]
    missing = call("GET", f"/sessions/{uuid.uuid4()}", token=bob)
    other = call("GET", f"/sessions/{sid}", token=bob)
    # The same answer as for a session that does not exist: nothing leaks.
    assert _error(other, 404, "not_found") == _error(missing, 404, "not_found")
    for action in ("grant", "end", "stop"):
        _error(call("POST", f"/sessions/{sid}/{action}", token=bob), 404, "not_found")


def test_a_monitor_reads_any_session(requested, monitor):
    sid = requested["session"]["id"]
    response = call("GET", f"/sessions/{sid}", token=monitor)
    assert response.status_code == 200 and response.json()["user"] == "alice"


# --- grant, end, stop ----------------------------------------------------------------------


def test_the_owner_gets_a_fresh_grant(requested, alice):
    sid = requested["session"]["id"]
    response = call("POST", f"/sessions/{sid}/grant", token=alice)
    assert response.status_code == 200
    task = response.json()["task"]
    assert task["grant"] != requested["task"]["grant"]
    grant = UserGrant.verify(task["grant"], platform_public_key(), vehicle_id=task["vehicle_id"])
    assert grant.session_id == sid and grant.role == "controller"


def test_a_monitor_cannot_take_a_controller_grant(requested, monitor):
    sid = requested["session"]["id"]
    _error(call("POST", f"/sessions/{sid}/grant", token=monitor), 403, "permission_denied")


def test_the_owner_ends_the_session_and_the_vehicle_is_free(requested, alice, drone):
    sid = requested["session"]["id"]
    response = call("POST", f"/sessions/{sid}/end", token=alice, body={"reason": "done flying"})
    assert response.status_code == 200
    assert response.json()["state"] == "ended" and response.json()["reason"] == "done flying"
    assert response.json()["ended_at"] and response.json()["assignments"][0]["active"] is False
    drone.refresh_from_db()
    assert drone.status == Vehicle.Status.IDLE
    # Over is over: no second end, no fresh grant.
    _error(call("POST", f"/sessions/{sid}/end", token=alice), 409, "session_state")
    _error(call("POST", f"/sessions/{sid}/grant", token=alice), 409, "session_state")


def test_ending_without_a_body_uses_a_default_reason(requested, alice):
    sid = requested["session"]["id"]
    response = call("POST", f"/sessions/{sid}/end", token=alice)
    assert response.json()["reason"] == "ended by the user"


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"reason": ""}, "reason"),
        ({"reason": 3}, "reason"),
        ({"reason": "x" * 301}, "reason"),
        ({"reason": None}, "reason"),
        ({"reason": "   "}, "reason"),
        ({"reason": "nul\x00"}, "reason"),
        ({"why": "x"}, "why"),
    ],
)
def test_an_invalid_reason_is_400(requested, alice, body, field):
    sid = requested["session"]["id"]
    response = call("POST", f"/sessions/{sid}/end", token=alice, body=body)
    error = _error(response, 400, "invalid_field")
    assert error["field"] == field


def test_a_monitor_must_stop_rather_than_end(requested, monitor):
    sid = requested["session"]["id"]
    _error(call("POST", f"/sessions/{sid}/end", token=monitor), 403, "permission_denied")


async def _receive(layer: Any, channel: str) -> dict[str, Any]:
    return await asyncio.wait_for(layer.receive(channel), 5)


def test_a_monitor_stops_a_session_with_the_failsafe(requested, monitor, drone, inbox):
    take = inbox(drone)
    (_task,) = take()  # the task went out: the agent holds the session
    sid = requested["session"]["id"]
    response = call("POST", f"/sessions/{sid}/stop", token=monitor)
    assert response.status_code == 200
    assert response.json()["state"] == "aborted"
    assert response.json()["reason"] == "stopped by a monitor (mona)"
    (sending,) = response.json()["delivery"]
    assert sending["state"] == "sending" and sending["vehicle"]["name"] == "drone-1"
    revoke = {
        "type": "revoke",
        "session_id": sid,
        "reason": "stopped by a monitor (mona)",
        "action": "land",
    }
    assert take() == [revoke]
    drone.refresh_from_db()
    assert drone.status == Vehicle.Status.RELEASING  # nobody gets it before it confirms
    take.ack(revoke)
    drone.refresh_from_db()
    assert drone.status == Vehicle.Status.IDLE
    (delivered,) = call("GET", f"/sessions/{sid}", token=monitor).json()["delivery"]
    assert delivered["state"] == "delivered" and delivered["action"] == "land"
    assert delivered["text"] == "The stop reached drone-1: it performs land"
    _error(call("POST", f"/sessions/{sid}/stop", token=monitor), 409, "session_state")


def test_a_stop_for_an_offline_vehicle_says_its_own_failsafe_holds(
    requested, monitor, drone, inbox
):
    take = inbox(drone)
    take()
    Vehicle.objects.filter(pk=drone.pk).update(status=Vehicle.Status.OFFLINE)
    sid = requested["session"]["id"]
    (offline,) = call("POST", f"/sessions/{sid}/stop", token=monitor).json()["delivery"]
    assert offline["state"] == "vehicle_offline"
    assert offline["text"] == (
        "drone-1 is offline: its own fail-safe (land) holds; the stop is delivered when it "
        "reconnects"
    )
    assert [m.kind for m in take.owed()] == ["revoke"]  # still owed


def test_a_stop_before_the_task_left_frees_the_vehicle_at_once(requested, monitor, drone, inbox):
    sid = requested["session"]["id"]
    response = call("POST", f"/sessions/{sid}/stop", token=monitor)
    assert response.json()["state"] == "aborted" and response.json()["delivery"] == []
    assert inbox(drone).owed() == []
    drone.refresh_from_db()
    assert drone.status == Vehicle.Status.IDLE


def test_what_request_end_and_stop_answer_is_what_reading_the_session_shows(
    drone, fly, alice, monitor
):
    # The answers are made from the rows just written; a read shows the same rows.
    def read(sid: str) -> Any:
        return call("GET", f"/sessions/{sid}", token=alice).json()

    created = call("POST", "/sessions", token=alice, body={"service": "fly", "target": TARGET})
    first = created.json()["session"]
    assert first == read(first["id"]) and len(first["log"]["events"]) == 5
    ended = call("POST", f"/sessions/{first['id']}/end", token=alice, body={"reason": "done"})
    assert ended.json() == read(first["id"]) and ended.json()["log"]["chain_ok"] is True
    assert [e["seq"] for e in ended.json()["log"]["events"]] == [1, 2, 3, 4, 5, 6]

    second = call("POST", "/sessions", token=alice, body={"service": "fly"}).json()["session"]
    stopped = call("POST", f"/sessions/{second['id']}/stop", token=monitor)
    assert stopped.json() == read(second["id"]) and stopped.json()["state"] == "aborted"


def test_a_client_holds_at_most_the_services_session_limit(requested, fly, alice):
    f.vehicle(station=f.station(), vtype=f.vehicle_type())
    second = call("POST", "/sessions", token=alice, body={"service": "fly"})
    _error(second, 409, "session_limit")
    assert "at most 1" in second.json()["error"]["message"]
    Service.objects.filter(pk=fly.pk).update(max_sessions_per_user=2)
    assert call("POST", "/sessions", token=alice, body={"service": "fly"}).status_code == 201


def test_the_owner_cannot_use_the_monitors_stop(requested, alice):
    sid = requested["session"]["id"]
    _error(call("POST", f"/sessions/{sid}/stop", token=alice), 403, "permission_denied")


# --- vehicles ------------------------------------------------------------------------------


def test_monitors_list_the_fleet_with_filters(drone, monitor):
    other = f.vehicle(station=f.station(name="Beach"), vtype=f.vehicle_type(), online=False)
    everything = call("GET", "/vehicles", token=monitor).json()["vehicles"]
    assert {v["name"] for v in everything} == {"drone-1", other.name}
    idle = call("GET", "/vehicles?status=idle", token=monitor).json()["vehicles"]
    assert [v["id"] for v in idle] == [str(drone.pk)]
    assert idle[0]["station"] == "Campus" and idle[0]["battery"] == 90.0
    beach = call("GET", "/vehicles?station=Beach", token=monitor).json()["vehicles"]
    assert [v["name"] for v in beach] == [other.name]
    assert call("GET", "/vehicles?station=Moon", token=monitor).json() == {"vehicles": []}


def test_an_unknown_status_filter_is_400(monitor):
    error = _error(call("GET", "/vehicles?status=flying", token=monitor), 400, "invalid_field")
    assert error["field"] == "status"


@pytest.mark.parametrize(
    ("query", "field"),
    [
        ("stauts=idle", "stauts"),
        ("status=idle&status=offline", "status"),
        ("station=%00", "station"),
    ],
)
def test_unknown_repeated_or_nul_query_parameters_are_400(monitor, query, field):
    error = _error(call("GET", f"/vehicles?{query}", token=monitor), 400, "invalid_field")
    assert error["field"] == field


def test_endpoints_without_query_parameters_refuse_them(fly, alice):
    error = _error(call("GET", "/services?page=2", token=alice), 400, "invalid_field")
    assert error["field"] == "page"


def test_clients_cannot_list_the_fleet(drone, alice):
    _error(call("GET", "/vehicles", token=alice), 403, "permission_denied")


# --- authentication ------------------------------------------------------------------------


def test_no_token_is_401_with_the_bearer_challenge(fly):
    response = call("GET", "/services")
    _error(response, 401, "not_authenticated")
    assert response["WWW-Authenticate"] == 'Bearer realm="iouv"'


@pytest.mark.parametrize(
    "header",
    ["Bearer", "Bearer ", "Token abc", "Basic YWxpY2U6cHc=", "Bearer iouv_x", "bearer nope"],
)
def test_a_malformed_authorization_header_is_401(alice, header):
    response = call("GET", "/services", HTTP_AUTHORIZATION=header)
    _error(response, 401, "invalid_token")
    assert response["WWW-Authenticate"] == 'Bearer realm="iouv", error="invalid_token"'


def test_a_revoked_token_is_401(alice):
    token_revoke(token=token_for_raw(alice))
    _error(call("GET", "/services", token=alice), 401, "invalid_token")


def test_a_forged_token_is_401(alice):
    prefix = alice.split("_", 2)[1]
    _error(call("GET", "/services", token=f"iouv_{prefix}_{'A' * 43}"), 401, "invalid_token")


def test_the_scheme_is_case_insensitive(fly, alice):
    assert call("GET", "/services", HTTP_AUTHORIZATION=f"bearer {alice}").status_code == 200


def test_a_logged_in_browser_without_a_token_is_401(drone, fly):
    """The session cookie is never an API credential, so there is no CSRF surface."""
    f.user(username="carol")
    browser = Client(enforce_csrf_checks=True)
    assert browser.login(username="carol", password="pw-for-tests")
    _error(call("GET", "/services", client=browser), 401, "not_authenticated")
    response = call("POST", "/sessions", client=browser, body={"service": "fly"})
    _error(response, 401, "not_authenticated")
    assert not Session.objects.exists()


def test_a_token_wins_over_another_users_cookie(fly, alice):
    f.user(username="carol", roles=(MONITOR,))
    browser = Client()
    browser.login(username="carol", password="pw-for-tests")
    # The token's user (alice, a client) is who acts, not the cookie's (a monitor).
    _error(call("GET", "/vehicles", client=browser, token=alice), 403, "permission_denied")


# --- JSON everywhere -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "path", ["/api/", "/api/nope", "/api/v1/services/", "/api/v2/services", "/api/v1/sessions/1"]
)
def test_unknown_paths_under_api_are_json_404(path, alice):
    response = Client().get(path, HTTP_AUTHORIZATION=f"Bearer {alice}")
    _error(response, 404, "not_found")


UNKNOWN_SESSION = uuid.UUID("5f0c3f5e-2d6b-4c1e-9a43-0d4c6f8a9b21")


@pytest.mark.parametrize(
    ("method", "path", "allow"),
    [
        ("DELETE", "/services", "GET"),
        ("GET", "/sessions", "POST"),
        # A fixed id: xdist's workers must collect the same test names.
        ("PUT", f"/sessions/{UNKNOWN_SESSION}", "GET"),
        ("GET", f"/sessions/{UNKNOWN_SESSION}/end", "POST"),
        ("POST", "/openapi.json", "GET"),
    ],
)
def test_wrong_methods_are_json_405_with_allow(method, path, allow, alice):
    response = call(method, path, token=alice)
    _error(response, 405, "method_not_allowed")
    assert response["Allow"] == allow


def test_a_bug_is_a_json_500(monkeypatch, alice, caplog):
    def explode(user):
        raise RuntimeError("boom")

    monkeypatch.setattr(api, "services_for_user", explode)
    response = call("GET", "/services", token=alice)
    error = _error(response, 500, "internal_error")
    assert "boom" not in error["message"]  # details go to the log, not to the client
    assert "boom" in caplog.text


# --- the OpenAPI document ------------------------------------------------------------------


def _api_routes() -> set[str]:
    """Every /api/v1 operation route of the URLconf, in OpenAPI's path syntax (the
    document, its page and ninja's root are not operations)."""
    # By its route: the resolver's text also holds the URLconf's file path, which may
    # say "api" anywhere (a checkout in a folder named "kapi").
    (api_resolver,) = [
        p
        for p in get_resolver().url_patterns
        if isinstance(p, URLResolver) and str(p.pattern) == "api/"
    ]
    (v1,) = [p for p in api_resolver.url_patterns if isinstance(p, URLResolver)]
    routes = set()
    for pattern in v1.url_patterns:
        if isinstance(pattern, URLPattern) and pattern.name not in NOT_OPERATIONS:
            route = "/" + re.sub(r"<\w+:", "{", str(pattern.pattern))
            routes.add(route.replace(">", "}"))
    return routes


NOT_OPERATIONS = {"openapi-json", "openapi-view", "api-root"}


def test_the_document_is_served_without_a_token_and_is_valid_openapi_3_1():
    response = Client().get("/api/v1/openapi.json")
    assert response.status_code == 200 and response["Content-Type"] == "application/json"
    assert response["Cache-Control"] == "public, max-age=300"
    document = response.json()
    assert document["openapi"] == "3.1.0"
    openapi_validate(document)  # raises on an invalid document
    assert document["servers"] == [{"url": "/api/v1"}]
    assert set(document["paths"]) == _api_routes()
    (scheme,) = document["components"]["securitySchemes"].values()
    assert scheme["type"] == "http" and scheme["scheme"] == "bearer"


def test_the_document_describes_the_errors_and_links_the_created_session():
    document = Client().get("/api/v1/openapi.json").json()
    create = document["paths"]["/sessions"]["post"]
    assert set(create["responses"]) == {
        *("201", "400", "401", "403", "409", "413", "422", "429", "500", "503")
    }
    assert create["responses"]["400"]["content"]["application/json"]["schema"] == {
        "$ref": "#/components/schemas/Error"
    }
    links = create["responses"]["201"]["links"]
    assert {link["operationId"] for link in links.values()} == {
        "session_read",
        "session_grant",
        "session_end",
        "session_stop",
    }
    assert "WWW-Authenticate" in create["responses"]["401"]["headers"]
    request = document["components"]["schemas"]["SessionRequest"]
    assert request["additionalProperties"] is False and request["required"] == ["service"]
    reason = document["components"]["schemas"]["EndRequest"]["properties"]["reason"]
    assert api.REASON_MAX == 300 and "300" in json.dumps(reason)


def test_the_interactive_docs_are_served_from_vendored_assets():
    page = Client().get("/api/v1/docs")
    assert page.status_code == 200
    # The portal's own policy, unrelaxed: the page needs no exception.
    policy = dict(d.strip().split(" ", 1) for d in page["Content-Security-Policy"].split(";"))
    assert policy["script-src"] == policy["style-src"] == "'self'"
    html = page.content.decode()
    assert "/static/ninja/swagger-ui-bundle.js" in html
    assert "/api/v1/openapi.json" in html
    assert "validator.swagger.io" not in html and '"validatorUrl": null' in html
    # Every URL on the page is the platform's own: no CDN.
    assert not re.findall(r"(?:src|href)=\"(?:https?:)?//", html)
    for asset in re.findall(r"(?:src|href)=\"(/static/[^\"]+)\"", html):
        assert finders.find(asset.removeprefix("/static/")), asset
    # No inline script (the policy would block it): only the page's settings, as data.
    inline = re.findall(r"<script(?![^>]*\bsrc=)([^>]*)>", html)
    assert inline == [' type="application/json" id="swagger-settings"']
    assert Client().post("/api/v1/docs").status_code == 405


# --- fuzzing the live API against its schema -----------------------------------------------


@pytest.fixture
def wsgi_app() -> Any:
    """Django as a WSGI app for schemathesis, on the test's database connection.

    Like django.test.Client, each request runs with close_old_connections unhooked:
    closing the connection after a request would take the test's transaction (and its
    rows) with it. The body is read and the response closed inside that window.
    """
    handler = WSGIHandler()

    def app(environ: dict[str, Any], start_response: Any) -> list[bytes]:
        request_started.disconnect(close_old_connections)
        request_finished.disconnect(close_old_connections)
        try:
            response = handler(environ, start_response)
            body = b"".join(response)
            response.close()
            return [body]
        finally:
            request_started.connect(close_old_connections)
            request_finished.connect(close_old_connections)

    return app


CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
    negative_data_rejection,
]


def _live_session(token: str) -> str:
    """A fresh session of the token's user on a vehicle of its own."""
    f.vehicle(station=f.station(), vtype=f.vehicle_type())
    response = call("POST", "/sessions", token=token, body={"service": "fly"})
    assert response.status_code == 201, response.content
    return response.json()["session"]["id"]


def _naming(pair: tuple[Any, str]) -> Any:
    """A generated session request, made to name a real service. ``fly-here``: the
    drone service without a target, which the drone can always serve; a generated
    target is anywhere on Earth, mostly out of the drone's range (422), so without it
    whether any request succeeds would depend on the fuzzer's version."""
    case, slug = pair
    if isinstance(case.body, dict):
        case.body["service"] = slug.removesuffix("-here")
        if slug.endswith("-here") and not _negative_body(case):
            case.body.pop("target", None)
            case.body.pop("preferences", None)
    return case


def _negative_body(case: Any) -> bool:
    """Whether the fuzzer made ``case``'s body break the schema on purpose. Such a
    body keeps its fault: dropping the faulty ``target`` would make a valid request
    that the fuzzer still expects to be refused."""
    return case.meta is not None and case.meta.is_negative_at(ParameterLocation.BODY)


def _fuzz(strategy: Any, *, headers: dict[str, str], seen: set[int]) -> None:
    """Send 20 cases of ``strategy`` (the same ones every run) and check each answer."""

    @given(case=strategy)
    @settings(
        max_examples=20,
        deadline=None,
        derandomize=True,
        suppress_health_check=list(HealthCheck),
    )
    def run(case: Any) -> None:
        seen.add(case.call_and_validate(headers=headers, checks=CHECKS).status_code)

    run()


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
def test_the_live_api_conforms_to_its_schema(wsgi_app, drone, fly, mode, settings):
    """No 5xx, only documented statuses, headers and bodies, and every invalid request
    refused; in positive mode every operation also succeeds at least once. The token's
    user is both a client and a monitor, so every endpoint answers for real."""
    # The drone stays online however long the fuzzer takes to reach the session
    # requests: on a loaded machine that was past the 6 s online window, and every
    # request was refused as "no vehicle is online and idle".
    settings.IOUV_OFFLINE_AFTER_S = 3600
    # One user asks for hundreds of sessions and grants: the rate limits are
    # test_throttle's.
    settings.RATELIMIT_ENABLE = False
    f.service("rescue", kind="rescue_at_sea")
    # Every session-id operation needs a live session of its own.
    Service.objects.filter(pk=fly.pk).update(max_sessions_per_user=1000)
    token = _token("fuzzer", CLIENT, MONITOR)
    auth = {"Authorization": f"Bearer {token}"}
    schema = schemathesis.openapi.from_wsgi("/api/v1/openapi.json", wsgi_app)
    # The token is ours to send (above): do not generate, or mutate, Authorization.
    schema.config.generation.update(with_security_parameters=False)
    statuses: dict[str, set[int]] = {}
    for result in schema.get_all_operations():
        operation = result.ok()
        if mode.is_negative and not (list(operation.iter_parameters()) or operation.body):
            continue  # nothing in the request to make invalid
        strategy = operation.as_strategy(generation_mode=mode)
        if mode.is_positive and "{session_id}" in operation.path:
            # Random ids find nothing: aim at a live session of the fuzzer's too.
            live = _live_session(token)
            strategy |= operation.as_strategy(path_parameters={"session_id": live})
        if mode.is_positive and operation.path == "/sessions":
            strategy = st.tuples(strategy, st.sampled_from(["fly", "fly-here", "rescue"])).map(
                _naming
            )
        seen = statuses.setdefault(f"{operation.method.upper()} {operation.path}", set())
        _fuzz(strategy, headers=auth, seen=seen)
    # Every operation but the document's own (schemathesis leaves it out; tested above).
    assert len(statuses) == (9 if mode.is_positive else 8), " ".join(statuses)
    if mode.is_positive:
        failing = {op: codes for op, codes in statuses.items() if not codes & {200, 201}}
        assert not failing, f"operations that never succeeded: {failing}"


#: The operations a created session's id leads to (the document's links).
SESSION_ID_OPERATIONS = {
    "GET /sessions/{session_id}",
    "POST /sessions/{session_id}/grant",
    "POST /sessions/{session_id}/end",
    "POST /sessions/{session_id}/stop",
}


def test_sequences_that_follow_the_links_conform_too(wsgi_app, fly, settings):
    """Schemathesis' state machine chains the calls through the document's links: a
    created session's id feeds the session-id endpoints, which then answer for real
    sessions in every state (assigned, ended, stopped) with no 5xx and only documented
    answers."""
    settings.IOUV_OFFLINE_AFTER_S = 3600  # as above: the vehicles stay online
    settings.RATELIMIT_ENABLE = False  # as above
    Service.objects.filter(pk=fly.pk).update(max_sessions_per_user=1000)
    token = _token("fuzzer", CLIENT, MONITOR)
    auth = {"Authorization": f"Bearer {token}"}
    schema = schemathesis.openapi.from_wsgi("/api/v1/openapi.json", wsgi_app)
    schema.config.generation.update(with_security_parameters=False)
    statuses: dict[str, set[int]] = {}

    class Workflow(schema.as_state_machine()):  # type: ignore[misc]
        def before_call(self, case: Any) -> None:
            if case.operation.path == "/sessions" and isinstance(case.body, dict):
                # A real service and a vehicle free to serve it, anywhere (see _naming).
                case.body["service"] = "fly"
                if not _negative_body(case):
                    case.body.pop("target", None)
                    case.body.pop("preferences", None)
                f.vehicle(station=f.station(), vtype=f.vehicle_type())

        def get_call_kwargs(self, case: Any) -> dict[str, Any]:
            return {"headers": auth}

        def validate_response(self, response: Any, case: Any, **kwargs: Any) -> None:
            label = f"{case.operation.method.upper()} {case.operation.path}"
            statuses.setdefault(label, set()).add(response.status_code)
            case.validate_response(response, checks=CHECKS, headers=auth)

    Workflow.run(
        settings=settings_for_machines(max_examples=25, stateful_step_count=6),
    )
    reached = {op: codes for op, codes in statuses.items() if op in SESSION_ID_OPERATIONS}
    assert set(reached) == SESSION_ID_OPERATIONS, statuses
    # Through the links the ids are real: answered for the session, not a 404.
    assert all(codes - {404} for codes in reached.values()), reached
    assert 200 in reached["GET /sessions/{session_id}"], reached


def settings_for_machines(**options: Any) -> Any:
    """Hypothesis settings for a state machine: the same sequences every run."""
    return settings(
        deadline=None, derandomize=True, suppress_health_check=list(HealthCheck), **options
    )
