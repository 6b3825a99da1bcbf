"""Flight records on the platform without servers: a batch kept once and chained, the
check, deletion by an admin and by the retention sweep (services.records.keeping)."""

from __future__ import annotations

import json
import threading
from datetime import timedelta
from typing import Any

import pytest
from django.contrib import admin
from django.contrib.messages.storage.fallback import FallbackStorage
from django.db import connection
from django.test import Client
from django.utils import timezone

from accounts.roles import ADMIN
from accounts.tokens import token_issue
from agents.protocol.messages import Record, RecordSample
from services.admin import SessionAdmin
from services.models import RecordBatch, Session
from services.records.keeping import record_batch_store, record_verify, records_expire
from services.sessions.ending import session_end
from services.web import record_views
from tests import factories as f
from tests.deployment import TARGET, limited_service, registered_vehicle, session_requested

pytestmark = pytest.mark.django_db


def _batch(session: Session, first: int, n: int = 3) -> Record:
    return Record(
        id=f"record:{session.pk}:{first}",
        session_id=str(session.pk),
        first=first,
        samples=[
            RecordSample(
                seq=first + i,
                t=1.8e9 + first + i,
                kind="telemetry",
                data={"lat": 40.0 + i / 1000, "lon": -8.0, "alt": 1.5},
            )
            for i in range(n)
        ],
    )


def test_a_batch_is_kept_once_and_its_digest_chained(live_session) -> None:
    session, vehicle = live_session
    assert record_batch_store(vehicle_id=vehicle, message=_batch(session, 1)).ok
    again = record_batch_store(vehicle_id=vehicle, message=_batch(session, 1))
    assert again.ok and again.detail == "already stored"
    assert record_batch_store(vehicle_id=vehicle, message=_batch(session, 4)).ok
    assert RecordBatch.objects.filter(session=session).count() == 2
    chained = [e.data for e in session.events.filter(kind="record_batch")]
    assert [(d["first"], d["last"]) for d in chained] == [(1, 3), (4, 6)]
    assert record_verify(session=session).ok


def test_a_gap_between_batches_fails_the_check(live_session) -> None:
    session, vehicle = live_session
    record_batch_store(vehicle_id=vehicle, message=_batch(session, 1))
    record_batch_store(vehicle_id=vehicle, message=_batch(session, 7))
    check = record_verify(session=session)
    assert not check.ok and check.problems == ["samples 4-6 were never received"]


@pytest.mark.postgres
@pytest.mark.django_db(transaction=True)
def test_a_batch_stored_while_the_record_is_checked_is_in_both_reads_or_neither(
    live_session,
) -> None:
    """The check reads the log, then the batches: a batch an agent stores between the
    two (its row and its log event in one transaction) is not found stored but unlogged,
    which a monitor would read as a record tampered with."""
    session, vehicle = live_session
    assert record_batch_store(vehicle_id=vehicle, message=_batch(session, 1)).ok
    stored: list[bool] = []

    def agent_stores() -> None:  # as the uplink does, on its own connection
        try:
            stored.append(record_batch_store(vehicle_id=vehicle, message=_batch(session, 4)).ok)
        finally:
            connection.close()

    def meanwhile(execute, sql, params, many, context):  # type: ignore[no-untyped-def]
        result = execute(sql, params, many, context)
        if not stored and '"services_sessionevent"' in sql:  # the log, just read
            writer = threading.Thread(target=agent_stores)
            writer.start()
            writer.join(30)
        return result

    with connection.execute_wrapper(meanwhile):
        check = record_verify(session=session)
    assert stored == [True]
    assert check.ok and check.batches == 1, check.problems  # the record as it was
    now = record_verify(session=session)
    assert now.ok and now.batches == 2, now.problems


def test_a_batch_for_another_vehicles_session_is_refused(live_session) -> None:
    session, _ = live_session
    other = f.vehicle(station=f.station(), vtype=f.vehicle_type(name="other type"))
    outcome = record_batch_store(vehicle_id=other.pk, message=_batch(session, 1))
    assert not outcome.ok and outcome.detail == "not a session of this vehicle"
    assert not RecordBatch.objects.exists()


def test_an_admin_deletes_a_record_and_the_log_says_so(live_session, rf) -> None:
    session, vehicle = live_session
    record_batch_store(vehicle_id=vehicle, message=_batch(session, 1))
    admin_user = f.user("root", roles=(ADMIN,))
    admin_user.is_superuser = True
    admin_user.save()
    request = rf.post("/admin/services/session/")
    request.user = admin_user
    request.session = {}
    request._messages = FallbackStorage(request)
    SessionAdmin(Session, admin.site).delete_flight_records(
        request, Session.objects.filter(pk=session.pk)
    )
    assert not RecordBatch.objects.filter(session=session).exists()
    deleted = session.events.get(kind="record_deleted")
    assert deleted.data == {"by": "root", "samples": 3}
    assert record_verify(session=session).ok  # the log keeps the digests, says it went


def test_records_past_their_retention_are_deleted(live_session, settings) -> None:
    session, vehicle = live_session
    record_batch_store(vehicle_id=vehicle, message=_batch(session, 1))
    settings.IOUV_RECORD_RETENTION_DAYS = 30
    assert records_expire(now=timezone.now() + timedelta(days=29)) == 0
    assert records_expire(now=timezone.now() + timedelta(days=31)) == 1
    assert not RecordBatch.objects.filter(session=session).exists()
    settings.IOUV_RECORD_RETENTION_DAYS = 0  # kept until an admin deletes them
    record_batch_store(vehicle_id=vehicle, message=_batch(session, 4))
    assert records_expire(now=timezone.now() + timedelta(days=3650)) == 0


def test_only_the_user_monitors_and_admins_open_a_record(live_session) -> None:
    session, vehicle = live_session
    record_batch_store(vehicle_id=vehicle, message=_batch(session, 1))
    url = f"/sessions/{session.pk}/record/"
    for user, status in [
        (session.user, 200),
        (f.user("mona", roles=("monitor",)), 200),
        (f.user("mallory"), 404),
    ]:
        client = Client()
        client.force_login(user)
        assert client.get(url).status_code == status, user
        assert client.get(url + "track.csv").status_code == status, user
    owner = Client()
    owner.force_login(session.user)
    assert owner.get(url + "tlog").status_code == 404  # no MAVLink log in this record
    assert owner.get(url + "nonsense").status_code == 404
    csv_lines = owner.get(url + "track.csv").content.decode().splitlines()
    assert len(csv_lines) == 4 and csv_lines[0].startswith("vehicle,seq,time_utc,lat,lon,alt")


def test_the_api_serves_the_record_to_its_user_and_monitors_only(live_session) -> None:
    session, vehicle = live_session
    record_batch_store(vehicle_id=vehicle, message=_batch(session, 1))
    base = f"/api/v1/sessions/{session.pk}/record"

    def get(user: object, path: str) -> Any:
        token = token_issue(user=user, name="tests")  # type: ignore[arg-type]
        return Client().get(path, headers={"authorization": f"Bearer {token}"})

    summary = get(session.user, base)
    assert summary.status_code == 200
    assert summary.json()["samples"] == {"telemetry": 3}
    assert summary.json()["verification"]["ok"] is True
    assert "tlog" not in summary.json()["exports"]
    kml = get(f.user("mona", roles=("monitor",)), summary.json()["exports"]["kml"])
    assert kml.status_code == 200
    assert kml["content-type"] == "application/vnd.google-earth.kml+xml"
    assert kml.content.count(b"<gx:coord>") == 3
    stranger = get(f.user("mallory"), base + "/gpx")
    assert stranger.status_code == 404 and stranger.json()["error"]["code"] == "not_found"
    assert get(session.user, base + "/tlog").status_code == 404


def test_the_replay_reads_the_samples_after_its_cursor_and_refuses_bad_input(
    live_session, monkeypatch
) -> None:
    session, vehicle = live_session
    record_batch_store(vehicle_id=vehicle, message=_batch(session, 1))
    client = Client()
    client.force_login(session.user)
    url = f"/sessions/{session.pk}/replay/samples"
    monkeypatch.setattr(record_views, "REPLAY_PAGE", 2)
    first = client.get(url).json()
    assert [s["seq"] for s in first["samples"]] == [1, 2] and first["more"] and first["live"]
    rest = client.get(url, {"after": first["next"]}).json()
    assert [s["seq"] for s in rest["samples"]] == [3] and not rest["more"]
    record_batch_store(vehicle_id=vehicle, message=_batch(session, 4, n=1))
    new = client.get(url, {"after": rest["next"]}).json()
    assert [s["seq"] for s in new["samples"]] == [4]
    assert new["samples"][0]["data"]["lat"] == 40.0

    bad = client.get(url, {"after": "-1"})
    assert bad.status_code == 400 and "whole number" in bad.json()["error"]
    stranger = Client()
    stranger.force_login(f.user("mallory"))
    assert stranger.get(url).status_code == 404
    assert stranger.get(f"/sessions/{session.pk}/replay/").status_code == 404


def test_the_replay_names_every_vehicle_of_the_session_once_their_roles_are_released() -> None:
    drone, boat = registered_vehicle(name="searcher"), registered_vehicle(name="carrier")
    service = limited_service(roles=[{"name": "search"}, {"name": "delivery"}])
    session = session_requested(user=f.user(), service=service, target=TARGET).session
    for vehicle in (boat, drone):
        record_batch_store(vehicle_id=vehicle.pk, message=_batch(session, 1, n=2))
    session_end(session=session, reason="the person was brought back", by_user=True)
    assert not session.assignments.filter(active=True).exists()

    client = Client()
    client.force_login(session.user)
    page = client.get(f"/sessions/{session.pk}/replay/").content.decode()
    start = page.index('<script id="replay-config" type="application/json">')
    config = json.loads(page[page.index(">", start) + 1 : page.index("</script>", start)])
    # In the order they were given their roles, whichever recorded first.
    assigned = [str(a.vehicle_id) for a in session.assignments.order_by("created_at", "pk")]
    names = {str(drone.pk): "searcher", str(boat.pk): "carrier"}
    assert config["vehicles"] == [{"id": v, "name": names[v]} for v in assigned]

    answer = client.get(f"/sessions/{session.pk}/replay/samples").json()
    assert {s["vehicle"] for s in answer["samples"]} == set(names)
    assert answer["vehicles"] == names and not answer["live"]
