"""Task deployment: signed vehicle tasks pushed on the uplink, user tasks, ending sessions.

What an agent would receive is read from the channel layer (Redis under bin/test), from
the same group the uplink consumer of the vehicle listens on.
"""

from __future__ import annotations

import time

import pytest
from django.conf import settings
from django.core.exceptions import ImproperlyConfigured

from accounts.roles import MONITOR
from agents.missions.return_home.spec import ReturnSpec
from agents.protocol import Limits, UserGrant, VehicleTask, generate_keypair
from fleet.models import Vehicle
from services.kinds import ServiceKind, UnknownKind, kind_named, kind_of, kind_register
from services.models import Session
from services.sessions.deployment import DeploymentError, InvalidTaskError, grant_issue
from services.sessions.ending import session_end, session_revoke
from services.sessions.signing import (
    platform_private_key,
    platform_public_key,
    platform_public_key_pem,
)
from services.sessions.states import SessionStateError
from tests import factories as f
from tests.deployment import (
    LIMITS,
    TARGET,
    limited_service,
    registered_vehicle,
    session_requested,
)

pytestmark = pytest.mark.django_db


@pytest.fixture
def deployed(inbox, committing):
    """(session, vehicle, user task, vehicle task) of a freshly deployed session."""
    vehicle = registered_vehicle()
    take = inbox(vehicle)
    with committing():
        opened = session_requested(
            user=f.user(username="alice"), service=limited_service(), target=TARGET
        )
    session, user_task = opened.session, opened.task
    (message,) = take()
    assert message["type"] == "task"
    task = VehicleTask.verify(message["token"], platform_public_key(), vehicle_id=str(vehicle.pk))
    return session, vehicle, user_task, task, take


def test_deploy_pushes_a_signed_task_with_the_service_limits(deployed):
    session, vehicle, _, task, _ = deployed
    assert task.session_id == str(session.pk) and task.vehicle_id == str(vehicle.pk)
    assert task.user == "alice"
    assert task.allowed_commands == ("up", "stop")
    assert task.limits == Limits(geofence_center=TARGET, **LIMITS)
    assert task.expires_at - task.issued_at == settings.IOUV_TASK_TTL_S
    assert abs(task.issued_at - time.time()) < 5

    session.refresh_from_db()
    assert session.state == Session.State.ASSIGNED  # active once the user connects
    logged = session.events.get(kind="task_deployed")
    assert logged.data["vehicle"] == str(vehicle.pk) and logged.data["nonce"] == task.nonce


def test_deploy_returns_a_user_task_with_a_controller_grant(deployed):
    session, vehicle, user_task, _, _ = deployed
    grant = UserGrant.verify(user_task.grant, platform_public_key(), vehicle_id=str(vehicle.pk))
    assert (grant.session_id, grant.user, grant.role) == (str(session.pk), "alice", "controller")
    assert grant.allowed_commands == ("up", "stop")
    assert grant.expires_at - grant.issued_at == settings.IOUV_GRANT_TTL_S
    assert user_task.expires_at == grant.expires_at
    assert user_task.session_id == str(session.pk) and user_task.vehicle_id == str(vehicle.pk)
    assert user_task.vehicle_name == vehicle.name
    assert user_task.control_url == "ws://10.0.0.7:8765/control"
    assert [c["name"] for c in user_task.commands] == ["up", "stop"]  # only what it may send
    assert user_task.telemetry == ("position", "battery")
    assert user_task.relay is False and user_task.role == "controller"


def test_tokens_never_reach_the_log(deployed):
    session, _, user_task, _, _ = deployed
    logged = str(list(session.events.values_list("data", flat=True)))
    assert user_task.grant not in logged
    assert user_task.grant.split(".")[1] not in logged


def test_geofence_is_centred_on_the_vehicle_without_a_target(inbox, committing):
    vehicle = registered_vehicle(at=(40.6320, -8.6570))
    take = inbox(vehicle)
    with committing():
        session_requested(user=f.user(), service=limited_service())
    (message,) = take()
    task = VehicleTask.verify(message["token"], platform_public_key(), vehicle_id=str(vehicle.pk))
    assert task.limits.geofence_center == (40.6320, -8.6570)


def test_no_radius_means_no_geofence(inbox, committing):
    vehicle = registered_vehicle()
    take = inbox(vehicle)
    service = limited_service(geofence_radius_m=None, max_altitude_m=None)
    with committing():
        session_requested(user=f.user(), service=service, target=TARGET)
    (message,) = take()
    task = VehicleTask.verify(message["token"], platform_public_key(), vehicle_id=str(vehicle.pk))
    assert task.limits.geofence_center is None and task.limits.geofence_radius_m is None
    assert task.limits.max_altitude_m is None


def test_relay_only_vehicle_gives_a_relay_user_task():
    vehicle = registered_vehicle()
    Vehicle.objects.filter(pk=vehicle.pk).update(control_url="")
    user_task = session_requested(user=f.user(), service=limited_service()).task
    assert user_task is not None and user_task.relay is True


def test_every_role_gets_a_task_and_the_user_controls_the_vehicle_role(inbox, committing):
    searcher = registered_vehicle(name="searcher")
    main = registered_vehicle(name="main")
    takes = {v.name: inbox(v) for v in (searcher, main)}
    service = limited_service(roles=[{"name": "search"}, {"name": "vehicle"}])
    with committing():
        opened = session_requested(user=f.user(), service=service, target=TARGET)
    session, user_task = opened.session, opened.task
    for vehicle in (searcher, main):
        (message,) = takes[vehicle.name]()
        VehicleTask.verify(message["token"], platform_public_key(), vehicle_id=str(vehicle.pk))
    held = {a.role: a.vehicle for a in session.assignments.all()}
    assert user_task.vehicle_id == str(held["vehicle"].pk)


def test_invalid_limits_fail_the_session_and_send_nothing():
    vehicle = registered_vehicle()
    with pytest.raises(InvalidTaskError, match="max_speed_mps") as refused:
        session_requested(user=f.user(), service=limited_service(max_speed_mps=0))
    session = refused.value.session
    assert session is not None
    session.refresh_from_db()
    assert session.state == Session.State.FAILED and "max_speed_mps" in session.reason
    assert not session.events.filter(kind="task_deployed").exists()
    assert Vehicle.objects.get(pk=vehicle.pk).status == Vehicle.Status.IDLE


def test_a_mission_its_kind_does_not_declare_is_never_signed(monkeypatch):
    vehicle = registered_vehicle()
    service = limited_service()
    kind = kind_of(service)
    assert ReturnSpec not in kind.missions
    monkeypatch.setattr(kind, "vehicle_mission", lambda *, assignment: ReturnSpec(id="m-1"))
    with pytest.raises(InvalidTaskError, match="does not deploy 'return' missions") as refused:
        session_requested(user=f.user(username="alice"), service=service, target=TARGET)
    session = refused.value.session
    assert session is not None
    session.refresh_from_db()
    assert session.state == Session.State.FAILED
    assert not session.events.filter(kind="task_deployed").exists()
    assert Vehicle.objects.get(pk=vehicle.pk).status == Vehicle.Status.IDLE


def test_a_kind_may_declare_only_missions_an_agent_has():
    class Private(ReturnSpec, frozen=True, kw_only=True, tag="private"):
        """A spec no folder under agents/missions/ declares."""

    class Rogue(ServiceKind):
        name = "rogue"
        label = "Rogue"
        missions = (Private,)

    with pytest.raises(ValueError, match="declares missions no agent has: Private"):
        kind_register(Rogue())
    with pytest.raises(UnknownKind):
        kind_named("rogue")


# --- grants -----------------------------------------------------------------------------


def test_grant_issue_gives_the_user_a_fresh_grant(deployed):
    session, vehicle, first, _, _ = deployed
    again = grant_issue(session=session, user=session.user)
    assert again.grant != first.grant
    grant = UserGrant.verify(again.grant, platform_public_key(), vehicle_id=str(vehicle.pk))
    assert grant.role == "controller" and grant.user == "alice"


def test_only_the_sessions_user_may_control(deployed):
    session, *_ = deployed
    with pytest.raises(DeploymentError, match="only the session's user"):
        grant_issue(session=session, user=f.user())


def test_viewers_may_watch_but_send_nothing(deployed):
    session, vehicle, *_ = deployed
    watcher = grant_issue(session=session, user=f.user(username="bob"), role="viewer")
    grant = UserGrant.verify(watcher.grant, platform_public_key(), vehicle_id=str(vehicle.pk))
    assert (grant.role, grant.user, grant.allowed_commands) == ("viewer", "bob", ())
    assert watcher.commands == ()
    with pytest.raises(DeploymentError, match="may not use"):
        grant_issue(session=session, user=f.user(roles=(MONITOR,)), role="viewer")
    with pytest.raises(DeploymentError, match="unknown role"):
        grant_issue(session=session, user=session.user, role="pilot")


def test_no_grant_for_a_final_session(deployed):
    session, *_ = deployed
    session_end(session=session, reason="user left", by_user=True)
    with pytest.raises(DeploymentError, match="ended: user left"):
        grant_issue(session=session, user=session.user)


# --- ending -----------------------------------------------------------------------------


def status(vehicle):
    return Vehicle.objects.get(pk=vehicle.pk).status


def test_session_end_sends_end_task_and_frees_the_vehicle_once_its_agent_confirms(
    deployed, committing
):
    session, vehicle, _, _, take = deployed
    with committing():
        session_end(session=session, reason="user ended the session", by_user=True)
    end = {"type": "end_task", "session_id": str(session.pk), "reason": "user ended the session"}
    assert take() == [end]
    session.refresh_from_db()
    assert session.state == Session.State.ENDED and session.reason == "user ended the session"
    assert session.events.filter(kind="state").last().data["by_user"] is True
    assert not session.assignments.filter(active=True).exists()
    # Nobody else gets the vehicle before its agent says it gave the session up.
    assert status(vehicle) == Vehicle.Status.RELEASING
    take.ack(end)
    assert status(vehicle) == Vehicle.Status.IDLE
    assert session.events.filter(kind="end_delivered").exists()
    with pytest.raises(SessionStateError):
        session_end(session=session, reason="again", by_user=True)


def test_session_revoke_sends_revoke_and_aborts(deployed, committing):
    session, vehicle, _, _, take = deployed
    with committing():
        session_revoke(session=session, reason="kill switch", action="return_to_home")
    revoke = {
        "type": "revoke",
        "session_id": str(session.pk),
        "reason": "kill switch",
        "action": "return_to_home",
    }
    assert take() == [revoke]
    session.refresh_from_db()
    assert session.state == Session.State.ABORTED and session.reason == "kill switch"
    assert status(vehicle) == Vehicle.Status.RELEASING
    take.ack(revoke)
    assert status(vehicle) == Vehicle.Status.IDLE
    delivered = session.events.get(kind="stop_delivered").data
    assert delivered["vehicle_name"] == vehicle.name and delivered["action"] == "return_to_home"


def test_a_task_that_never_left_is_withdrawn_and_the_vehicle_freed_at_once(inbox, committing):
    """The agent never heard of the session: there is nothing to take back."""
    vehicle = registered_vehicle()
    take = inbox(vehicle)
    with committing():
        session = session_requested(
            user=f.user(username="alice"), service=limited_service(), target=TARGET
        ).session
        session_revoke(session=session, reason="kill switch", action="land")
    assert take.owed() == []
    assert status(vehicle) == Vehicle.Status.IDLE


def test_messages_to_an_agent_are_owed_in_order_until_acknowledged(deployed, committing):
    session, _vehicle, _, _, take = deployed
    with committing():
        session_end(session=session, reason="done", by_user=True)
    (end,) = take()
    # Not acknowledged: still owed, and a second session's task queues behind it.
    assert [m.kind for m in take.owed()] == ["end_task"]
    take.ack(end)
    assert take.owed() == []


def test_session_revoke_refuses_an_unknown_action(deployed):
    session, *_ = deployed
    with pytest.raises(ValueError, match="action"):
        session_revoke(session=session, reason="x", action="explode")
    session.refresh_from_db()
    assert session.state == Session.State.ASSIGNED


# --- the signing key --------------------------------------------------------------------


def test_a_dev_key_is_generated_once_with_mode_0600(settings, tmp_path):
    settings.IOUV_SIGNING_KEY = ""
    settings.DEV_SECRETS = True
    settings.IOUV_SIGNING_KEY_PATH = tmp_path / "keys" / "signing.pem"
    pem = platform_public_key_pem()
    assert (settings.IOUV_SIGNING_KEY_PATH.stat().st_mode & 0o777) == 0o600
    platform_private_key.cache_clear()
    assert platform_public_key_pem() == pem  # read back, not regenerated


def test_the_configured_key_wins(settings, tmp_path):
    private_pem, public_pem = generate_keypair()
    settings.IOUV_SIGNING_KEY = private_pem
    settings.IOUV_SIGNING_KEY_PATH = tmp_path / "unused.pem"
    assert platform_public_key_pem() == public_pem
    assert not settings.IOUV_SIGNING_KEY_PATH.exists()


def test_no_key_outside_dev_is_a_configuration_error(settings, tmp_path):
    settings.IOUV_SIGNING_KEY = ""
    settings.DEV_SECRETS = False
    settings.IOUV_SIGNING_KEY_PATH = tmp_path / "signing.pem"
    with pytest.raises(ImproperlyConfigured, match="IOUV_SIGNING_KEY"):
        platform_private_key()
    settings.IOUV_SIGNING_KEY = "not a pem"
    with pytest.raises(ImproperlyConfigured, match="IOUV_SIGNING_KEY"):
        platform_private_key()
